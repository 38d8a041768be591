"""Training from an HDF5 dataset larger than the memory a run may use.

Generates a lifted-pendulum dataset of about ``--gib`` GiB (almost all of it the coarse fields and
velocities that training reads), then trains on it in child processes placed in a memory cgroup limited to
``--limit-gib`` GiB (the cgroup counts page cache too, as a cluster's does), and reports, per run, peak RSS,
the cgroup's peak usage, the loader's throughput alone and the training throughput (snapshots/s):

- ``lazy``: the default, snapshots streamed from the file (one read-only handle per process);
- ``lazy, 2 workers``: the same with two DataLoader workers (one handle each);
- ``in_memory`` under the limit: expected to be killed;
- ``in_memory`` without a limit: the baseline the lazy throughput is compared with, as a ratio.

    python -m experiments.streaming                    # 6 GiB of data, 1.5 GiB limit, 40 training steps
    python -m experiments.streaming --gib 0.3 --limit-gib 0.2 --steps 5     # smoke

Needs a writable memory cgroup (v2 ``/sys/fs/cgroup`` or v1 ``/sys/fs/cgroup/memory``, usually root);
without one it says so and exits. Writes outputs/streaming/results.json and summary.md (the table of the docs).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Optional

ROOT = Path(__file__).resolve().parents[1]
# fine grid 8² (tiny), coarse grid 64² (what training reads), 100 samples all used for training
GEN = dict(n_val=2, n_test=2, n_times=100, dt=0.05, train_times=100, fine_resolution=8, coarse_resolution=64,
           observed_fraction=0.0625, seed=0)


def bytes_per_trajectory() -> int:
    """float32 (fine + coarse) × (fields + velocities) × samples × points."""
    points = GEN["fine_resolution"] ** 2 + GEN["coarse_resolution"] ** 2
    return 4 * 2 * GEN["n_times"] * points


# ---------------------------------------------------------------------------------------------------
# memory cgroups
# ---------------------------------------------------------------------------------------------------
class MemoryCgroup:
    """A fresh memory cgroup (v2 or v1) with a hard limit; children join it before they exec."""

    def __init__(self, limit_bytes: int) -> None:
        name = f"lnf-streaming-{uuid.uuid4().hex[:8]}"
        v2, v1 = Path("/sys/fs/cgroup"), Path("/sys/fs/cgroup/memory")
        if (v2 / "cgroup.controllers").exists() and "memory" in (v2 / "cgroup.controllers").read_text():
            self.path, self.limit_file, self.peak_file = v2 / name, "memory.max", "memory.peak"
        elif (v1 / "memory.limit_in_bytes").exists():
            self.path, self.limit_file, self.peak_file = v1 / name, "memory.limit_in_bytes", "memory.max_usage_in_bytes"
        else:
            raise RuntimeError("no memory cgroup controller under /sys/fs/cgroup")
        self.path.mkdir()
        try:
            (self.path / self.limit_file).write_text(str(limit_bytes))
        except OSError:  # e.g. a v2 hierarchy whose memory controller is not delegated here
            self.remove()
            raise
        if (self.path / "memory.memsw.limit_in_bytes").exists():  # v1: no escape into swap
            try:
                (self.path / "memory.memsw.limit_in_bytes").write_text(str(limit_bytes))
            except OSError:
                pass
        if (self.path / "memory.swap.max").exists():  # v2
            (self.path / "memory.swap.max").write_text("0")

    def join(self) -> None:  # runs in the child between fork and exec
        (self.path / "cgroup.procs").write_text(str(os.getpid()))

    def peak(self) -> Optional[int]:
        try:
            return int((self.path / self.peak_file).read_text())
        except (OSError, ValueError):
            return None

    def remove(self) -> None:
        try:
            self.path.rmdir()
        except OSError:
            pass


# ---------------------------------------------------------------------------------------------------
# the child: a loader pass, then training steps
# ---------------------------------------------------------------------------------------------------
def child(args: argparse.Namespace) -> None:
    import lightning.pytorch as pl
    import torch

    from lnf.training.datamodule import SnapshotDataModule
    from lnf.training.module import LNFModule

    torch.set_num_threads(2)
    n_train = int(args.n_train)
    started = time.perf_counter()
    dm = SnapshotDataModule({"_target_": "lnf.scenes.LiftedPendulum"}, path=args.path, on_mismatch="error",
                            batch_size=args.batch_size, num_workers=args.workers, in_memory=args.mode == "in_memory",
                            n_train=n_train, **GEN)
    loader = dm.train_dataloader()
    setup_seconds = time.perf_counter() - started
    # the loader alone: reads, masking, collation
    t0, seen = time.perf_counter(), 0
    for i, batch in enumerate(loader):
        seen += len(batch)
        if i + 1 >= args.loader_batches:
            break
    loader_rate = seen / (time.perf_counter() - t0)

    class Clock(pl.Callback):
        """Snapshots/s over the training steps after the first (warm-up) ones."""

        def __init__(self) -> None:
            self.start, self.count = None, 0

        def on_train_batch_start(self, trainer, module, batch, batch_idx):
            if batch_idx == args.warmup:
                self.start = time.perf_counter()

        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
            if batch_idx >= args.warmup:
                self.count += len(batch)

    from omegaconf import OmegaConf

    conf = lambda name: OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / f"{name}.yaml"))  # noqa: E731
    model = {**conf("model/lnf"), **conf("experiment/pendulum").get("model", {})}  # the pendulum's w0, not auto
    module = LNFModule(scene={"_target_": "lnf.scenes.LiftedPendulum"}, model=model,
                       quadrature=conf("quadrature/gauss_legendre"), optimizer=conf("optimizer/adam"))
    clock = Clock()
    trainer = pl.Trainer(accelerator="cpu", devices=1, max_steps=args.warmup + args.steps, limit_val_batches=0,
                         logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, callbacks=[clock], use_distributed_sampler=False)
    trainer.fit(module, train_dataloaders=loader)
    train_rate = clock.count / (time.perf_counter() - clock.start)
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    workers = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
    print("RESULT " + json.dumps({"setup_seconds": setup_seconds, "loader_snapshots_per_s": loader_rate,
                                  "train_snapshots_per_s": train_rate, "peak_rss_bytes": own,
                                  "worker_peak_rss_bytes": workers if args.workers else 0}))


# ---------------------------------------------------------------------------------------------------
# the parent
# ---------------------------------------------------------------------------------------------------
def run_label(row: dict[str, Any], limit_gib: float) -> str:
    """'streaming, 2 DataLoader workers, 1.5 GiB limit', 'in memory, no limit (the baseline, same run)'."""
    parts = ["streaming" if row["mode"] == "lazy" else "in memory"]
    parts += [f"{row['workers']} DataLoader workers"] if row["workers"] else []
    parts += [f"{limit_gib:g} GiB limit"] if row["limit_bytes"] else ["no limit (the baseline, same run)"]
    return ", ".join(parts)


def summary_text(result: dict[str, Any], limit_gib: float, command: str) -> str:
    """The run's table in Markdown, with the machine and the command (what results_tables.py reads)."""
    gib = 2 ** 30
    gen = result["generation"]

    def thousands(x: float) -> str:  # 1 935, as the docs print it
        return f"{x:,.0f}".replace(",", " ")

    head = (f"run ({result['dataset_bytes'] / gib:.2f} GiB dataset: {thousands(result['n_train'])} training "
            f"trajectories × {gen['n_times']} samples × {gen['coarse_resolution']}² points)")
    lines = [f"| {head} | peak RSS | cgroup peak | loader alone [snapshots/s] | training [snapshots/s] | "
             "training vs in-memory |", "|---|---|---|---|---|---|"]
    for row in result["runs"]:
        label = run_label(row, limit_gib)
        if "error" in row:
            why = "killed by the OOM killer" if row["returncode"] == -9 else "failed"
            lines.append(f"| {label} | {why} after {row['wall_seconds']:.0f} s |  |  |  |  |")
            continue
        rss = f"{(row['peak_rss_bytes'] + row['worker_peak_rss_bytes']) / gib:.2f} GiB"
        rss += " (process + workers)" if row["workers"] else ""
        cgroup = f"{row['cgroup_peak_bytes'] / gib:.2f} GiB" if row["cgroup_peak_bytes"] else ""
        ratio = f"{row['train_rate_vs_in_memory']:.2f}" if "train_rate_vs_in_memory" in row else ""
        lines.append(f"| {label} | {rss} | {cgroup} | {thousands(row['loader_snapshots_per_s'])} | "
                     f"{row['train_snapshots_per_s']:.1f} | {ratio} |")
    machine = result["machine"]
    return (f"# Training from a dataset larger than the memory limit\n\nMachine: {machine['platform']}, "
            f"{machine['cpus']} CPUs. Command: `{command}`.\n\n{result['steps']} timed steps at batch "
            f"{result['batch_size']} per run, after warm-up steps; the limit is a memory cgroup (page cache "
            f"included).\n\n" + "\n".join(lines) + "\n")


def make_dataset(gib: float, data_dir: Path) -> tuple[Path, int]:
    from lnf.dataset import DatasetConfig, default_path, ensure_dataset
    from lnf.scenes import LiftedPendulum

    n_train = max(int(gib * 2 ** 30 / bytes_per_trajectory()), 4)
    scene, cfg = LiftedPendulum(), DatasetConfig(n_train=n_train, **GEN)
    path = default_path(data_dir, scene, cfg)
    t0 = time.perf_counter()
    ensure_dataset(scene, cfg, path)
    print(f"dataset {path}: {path.stat().st_size / 2 ** 30:.2f} GiB, {n_train} training trajectories "
          f"({time.perf_counter() - t0:.0f} s to generate or check)", flush=True)
    return path, n_train


def run_child(args: argparse.Namespace, path: Path, n_train: int, mode: str, workers: int,
              limit: Optional[int]) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "experiments.streaming", "--child", "--mode", mode, "--workers", str(workers),
           "--path", str(path), "--n-train", str(n_train), "--steps", str(args.steps), "--warmup", str(args.warmup),
           "--batch-size", str(args.batch_size), "--loader-batches", str(args.loader_batches)]
    group = MemoryCgroup(limit) if limit else None
    label = f"{mode}" + (f", {workers} workers" if workers else "") + (f", limit {limit / 2 ** 30:.2f} GiB" if limit else ", no limit")
    print(f"running {label} ...", flush=True)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, preexec_fn=group.join if group else None)
    row: dict[str, Any] = {"mode": mode, "workers": workers, "limit_bytes": limit, "returncode": proc.returncode,
                           "wall_seconds": time.perf_counter() - t0, "cgroup_peak_bytes": group.peak() if group else None}
    if group:
        group.remove()
    lines = [l for l in proc.stdout.splitlines() if l.startswith("RESULT ")]
    if proc.returncode == 0 and lines:
        row.update(json.loads(lines[-1][len("RESULT "):]))
    else:
        row["error"] = "killed by the out-of-memory killer (SIGKILL)" if proc.returncode == -9 else proc.stderr[-1500:]
    print(f"  -> {json.dumps({k: v for k, v in row.items() if k != 'error'})}" + (f"\n  {row['error']}" if "error" in row else ""),
          flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.streaming", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gib", type=float, default=6.0, help="dataset size [GiB]")
    parser.add_argument("--limit-gib", type=float, default=1.5, help="memory limit of a training process [GiB]")
    parser.add_argument("--steps", type=int, default=40, help="timed training steps (after --warmup)")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--loader-batches", type=int, default=200, help="batches of the loader-only pass")
    parser.add_argument("--runs", default="lazy,lazy-workers,in_memory-limited,in_memory",
                        help="which runs (default all; in_memory, the baseline, is required)")
    parser.add_argument("--data-dir", type=Path, default=ROOT / "data" / "streaming")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "streaming" / "results.json")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--mode", default="lazy", help=argparse.SUPPRESS)
    parser.add_argument("--workers", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--path", help=argparse.SUPPRESS)
    parser.add_argument("--n-train", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args)
        return
    limit = int(args.limit_gib * 2 ** 30)
    try:
        MemoryCgroup(limit).remove()
    except (OSError, RuntimeError) as exc:
        sys.exit(f"streaming.py needs a writable memory cgroup to place the limit ({exc}); run it as root on a "
                 f"machine with cgroups, or see docs/scaling.md for the numbers measured on ours")
    path, n_train = make_dataset(args.gib, args.data_dir)
    runs = {"lazy": ("lazy", 0, limit), "lazy-workers": ("lazy", 2, limit),
            "in_memory-limited": ("in_memory", 0, limit), "in_memory": ("in_memory", 0, None)}
    chosen = [r.strip() for r in args.runs.split(",") if r.strip()]
    unknown = sorted(set(chosen) - set(runs))
    if unknown or "in_memory" not in chosen:
        sys.exit(f"--runs {args.runs!r}: expected a comma list of {', '.join(runs)} that includes in_memory (the "
                 f"baseline of the ratios){'; unknown: ' + ', '.join(unknown) if unknown else ''}")
    rows = [run_child(args, path, n_train, *runs[name]) for name in runs if name in chosen]
    base = rows[-1]
    for row in rows:
        if "train_snapshots_per_s" in row and "train_snapshots_per_s" in base:
            row["train_rate_vs_in_memory"] = row["train_snapshots_per_s"] / base["train_snapshots_per_s"]
            row["loader_rate_vs_in_memory"] = row["loader_snapshots_per_s"] / base["loader_snapshots_per_s"]
    result = {"dataset": str(path), "dataset_bytes": path.stat().st_size, "n_train": n_train, "generation": GEN,
              "limit_bytes": limit, "steps": args.steps, "batch_size": args.batch_size, "runs": rows,
              "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count()},
              "date": time.strftime("%Y-%m-%d")}
    from lnf.tempfiles import write_text_atomic

    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out, json.dumps(result, indent=2))
    command = " ".join(["python -m experiments.streaming", *sys.argv[1:]])
    write_text_atomic(args.out.with_name("summary.md"), summary_text(result, args.limit_gib, command))
    print(f"\ndataset {path.stat().st_size / 2 ** 30:.2f} GiB, limit {args.limit_gib:g} GiB (cgroup, page cache included)")
    print(f"{'run':34s} {'peak RSS':>9s} {'cgroup':>8s} {'loader/s':>9s} {'train/s':>8s} {'vs in-mem':>9s}")
    for row in rows:
        name = row["mode"] + (f" ({row['workers']} workers)" if row["workers"] else "") + (" limited" if row["limit_bytes"] else " unlimited")
        if "error" in row:
            print(f"{name:34s} {row['error'][:60]}")
            continue
        rss = (row["peak_rss_bytes"] + row["worker_peak_rss_bytes"]) / 2 ** 30
        cg = f"{row['cgroup_peak_bytes'] / 2 ** 30:.2f}G" if row["cgroup_peak_bytes"] else "-"
        print(f"{name:34s} {rss:8.2f}G {cg:>8s} {row['loader_snapshots_per_s']:9.0f} {row['train_snapshots_per_s']:8.1f} "
              f"{row.get('train_rate_vs_in_memory', float('nan')):9.2f}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
