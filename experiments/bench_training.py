"""Training step and decoding against their FLOP bounds, and against a baseline commit measured in the same run.

    python -m experiments.bench_training                       # this checkout alone
    python -m experiments.bench_training --baseline 75a887b    # + that commit, in a temporary git worktree
    python -m experiments.bench_training --smoke               # tiny sizes (the test suite)

Measures, with the pendulum experiment's defaults (width 256, depth 2, K = 3, d = 1, a batch of 32 snapshots
observed on 256 points with velocities; decoding 16 trajectories × 100 frames on the 64² test grid):

* one training step (losses, backward, Adam update), median of repeated steps [s];
* the matmul FLOPs the step needs (every forward-mode jet's products, backward counted as twice the forward),
  divided by this machine's best float32 GEMM throughput measured in the same run: the FLOP bound [s];
* decoding (values only) of the same frames, and its bound;
* the same frames decoded through a Chebyshev table of φ in the code, where the checkout has one.

A baseline commit is checked out with ``git worktree`` into a temporary folder and measured by the same
function in a subprocess with that folder first on ``PYTHONPATH`` (same machine, same minute); the table
gives each figure of this checkout as a ratio to the baseline's. Rounds alternate the checkouts
(``--rounds``, default 3) and keep each one's fastest time, so a busy moment on a shared machine does not decide. Jets per step are counted by wrapping
``ModulatedSiren.jet`` for one step, so the count is the code's, not a formula's. Prints a Markdown table and
writes it with its provenance as ``summary.md``, beside the raw ``bench_training.json``, into
``outputs/studies/bench_training/`` (or ``--out DIR``), atomically; ``python -m experiments.results_tables
--collect bench_training`` copies them into ``results/`` for the documentation's table.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def _median_seconds(fn, repeats: int, warmup: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    times.sort()
    return times[len(times) // 2]


def matmul_peak() -> float:
    """Best float32 GEMM throughput [FLOP/s] over a few large shapes."""
    import torch

    best = 0.0
    for m, k, n in [(2048, 256, 256), (8192, 256, 256), (4096, 512, 512), (2048, 2048, 2048)]:
        a, b = torch.randn(m, k), torch.randn(k, n)
        seconds = _median_seconds(lambda: a @ b, repeats=7, warmup=2)
        best = max(best, 2.0 * m * k * n / seconds)
    return best


def jet_flops(rows: int, width: int, depth: int, in_dim: int, out_dim: int, streams: int) -> float:
    """Matmul FLOPs of one forward jet at `rows` = batch × points: the first layer's values (its derivatives are
    constants), `streams` (value + directions) through the hidden and output layers."""
    return 2.0 * rows * (in_dim * width + (depth - 1) * streams * width * width + streams * width * out_dim)


def measure(size: dict[str, int], threads: int) -> dict[str, Any]:
    """Time one training step and one decoding of the sizes in `size` with the lnf on sys.path."""
    import numpy as np
    import torch

    import lnf
    from lnf.model import LagrangianNeuralField
    from lnf.quadrature import GaussLegendre, midpoint_grid
    from lnf.scenes import LiftedPendulum
    from lnf.siren import ModulatedSiren

    torch.manual_seed(0)
    torch.set_num_threads(threads)
    try:  # the allocator setting of the entry points, where this checkout has it
        from lnf.allocator import keep_freed_memory
        allocator = keep_freed_memory()
    except ImportError:
        allocator = False
    scene = LiftedPendulum()
    W, L, K, B, N = size["width"], size["depth"], size["K"], size["batch"], size["points"]
    model = LagrangianNeuralField(scene, latent_dim=1, width=W, depth=L, reduction_steps=K,
                                  quadrature=GaussLegendre(8).build(scene.bounds))
    rng = np.random.default_rng(0)
    coarse = midpoint_grid(32, scene.bounds).numpy()
    pts = np.stack([coarse[rng.choice(len(coarse), N, replace=False)] for _ in range(B)])
    states = np.stack([rng.uniform(-1.5, 1.5, B), rng.uniform(-3, 3, B)], -1)
    q, qdot = [], []
    for b in range(B):
        v, dv = scene.fields(states[b], pts[b])
        q.append(v)
        qdot.append(dv)
    points = torch.as_tensor(pts, dtype=torch.float32)
    values = torch.as_tensor(np.stack(q), dtype=torch.float32)
    velocities = torch.as_tensor(np.stack(qdot), dtype=torch.float32)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def step() -> None:
        opt.zero_grad(set_to_none=True)
        model.losses(points, values, velocities)["loss"].backward()
        opt.step()

    jets: list[int] = []  # streams (1 + directions) of every jet of one step
    original = ModulatedSiren.jet

    def counting(self, codes, pts_, order=1, spatial=False):
        jets.append(1 + (self.latent_dim if order >= 1 else 0) + (self.in_dim if spatial else 0))
        return original(self, codes, pts_, order=order, spatial=spatial)

    ModulatedSiren.jet = counting
    try:
        step()
    finally:
        ModulatedSiren.jet = original
    step_flops = 3.0 * sum(jet_flops(B * N, W, L, 2, 1, s) for s in jets)  # backward ≈ 2 × forward
    step_seconds = _median_seconds(step, repeats=size["repeats"], warmup=2)

    grid = midpoint_grid(size["grid"], scene.bounds).float()
    frames = size["trajectories"] * size["frames"]
    codes = 0.5 * torch.randn(frames, 1)
    chunk = max(1, size["decode_rows"] // len(grid))

    def decode() -> None:
        with torch.no_grad():
            for start in range(0, frames, chunk):
                model.field(codes[start:start + chunk], grid)

    decode_flops = jet_flops(frames * len(grid), W, L, 2, 1, 1)
    decode_seconds = _median_seconds(decode, repeats=3, warmup=1)
    table: dict[str, Any] = {}
    try:  # tabulated decoding of the same frames, where this checkout has it: the table's build included
        from lnf.decoding_table import DecodingTable, code_box
    except ImportError:
        DecodingTable = None
    if DecodingTable is not None:
        def tabulated() -> None:
            with torch.no_grad():
                low, high = code_box(codes)
                t = DecodingTable.build(lambda c: model.field(c, grid), low, high, codes, len(grid), 1)
                for start in range(0, frames, chunk):
                    t(codes[start:start + chunk])
                table.update(nodes=t.n, error=t.error)

        table["seconds"] = _median_seconds(tabulated, repeats=3, warmup=1)
    return {"lnf_version": lnf.__version__, "lnf_path": str(Path(lnf.__file__).parent), "jets_per_step": len(jets),
            "step_flops": step_flops, "step_seconds": step_seconds, "decode_flops": decode_flops,
            "decode_seconds": decode_seconds, "threads": threads,
            "keeps_freed_memory": allocator,
            **({"table_decode_seconds": table["seconds"], "table_nodes": table["nodes"],
                "table_error": table["error"]} if table else {})}


SIZES = {
    "default": dict(width=256, depth=2, K=3, batch=32, points=256, repeats=15, grid=64, trajectories=16, frames=100,
                    decode_rows=1 << 16),
    "smoke": dict(width=32, depth=2, K=2, batch=4, points=32, repeats=3, grid=8, trajectories=2, frames=5,
                  decode_rows=1 << 10),
}


def baseline_worktree(rev: str, into: Path) -> Path:
    """`rev` checked out (detached) under `into` with git worktree; the caller removes it."""
    path = into / "baseline"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--force", str(path), rev], check=True,
                   capture_output=True, text=True)
    return path


def measure_in(checkout: Path, mode: str, threads: int) -> dict[str, Any]:
    """`measure` (this file's, imported from this checkout's experiments/ as the module `bench_training`) run in a
    subprocess with `checkout` first on PYTHONPATH (the lnf package found there, not this one); the caller's own
    PYTHONPATH entries follow."""
    path = [str(checkout), str(Path(__file__).resolve().parent), os.environ.get("PYTHONPATH", "")]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in path if p)}
    code = ("import json, sys; sys.meta_path = [f for f in sys.meta_path if 'editable' not in repr(f).lower()];"
            "import bench_training as b;"
            "print('RESULT' + json.dumps(b.measure(b.SIZES[sys.argv[1]], int(sys.argv[2]))))")
    proc = subprocess.run([sys.executable, "-c", code, mode, str(threads)], env=env, capture_output=True, text=True,
                          cwd=str(checkout))
    if proc.returncode != 0:
        sys.exit(f"bench_training.py: measuring {checkout} failed:\n{proc.stderr[-3000:]}")
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT")][-1]
    result = json.loads(line[len("RESULT"):])
    if Path(result["lnf_path"]).resolve() != (checkout / "lnf").resolve():
        sys.exit(f"bench_training.py: the subprocess imported lnf from {result['lnf_path']}, not {checkout / 'lnf'}")
    return result


def table(rows: dict[str, dict[str, Any]], peak: float) -> str:
    cols = ["jets per step", "step [ms]", "step bound [ms]", "step / bound", "GFLOP per step",
            "decode [s]", "decode bound [s]", "decode / bound"]
    out = "| checkout | " + " | ".join(cols) + " |\n|---|" + "---|" * len(cols) + "\n"
    for name, r in rows.items():
        sb, db = r["step_flops"] / peak, r["decode_flops"] / peak
        vals = [f"{r['jets_per_step']}", f"{1e3 * r['step_seconds']:.1f}", f"{1e3 * sb:.1f}",
                f"{r['step_seconds'] / sb:.2f}", f"{r['step_flops'] / 1e9:.2f}", f"{r['decode_seconds']:.2f}",
                f"{db:.2f}", f"{r['decode_seconds'] / db:.2f}"]
        out += f"| {name} | " + " | ".join(vals) + " |\n"
    tabulated = {name: r for name, r in rows.items() if "table_decode_seconds" in r}
    if tabulated:
        out += ("\nThe same frames decoded through a Chebyshev table of φ in the code (lnf/decoding_table.py; the "
                "time includes building the table):\n\n| checkout | tabulated decode [s] | nodes | error (of the "
                "largest field) | × exact decoding |\n|---|---|---|---|---|\n")
        for name, r in tabulated.items():
            out += (f"| {name} | {r['table_decode_seconds']:.3f} | {r['table_nodes']} | {r['table_error']:.1e} | "
                    f"{r['table_decode_seconds'] / r['decode_seconds']:.3f} |\n")
    if "baseline" in rows and "this checkout" in rows:
        a, b = rows["this checkout"], rows["baseline"]
        out += ("\nThis checkout against the baseline: training step time × "
                f"{a['step_seconds'] / b['step_seconds']:.2f}, FLOPs per step × {a['step_flops'] / b['step_flops']:.2f}, "
                f"decoding time × {a['decode_seconds'] / b['decode_seconds']:.2f}.\n")
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench_training", description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", help="a git revision to measure in the same run (e.g. a commit of main)")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, for the test suite")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="torch threads (default: all cores)")
    parser.add_argument("--rounds", type=int, default=3, help="alternating measurement rounds (best of each kept)")
    parser.add_argument("--out", type=Path, help="folder for bench_training.json and summary.md (default "
                        "outputs/studies/bench_training)")
    args = parser.parse_args(argv)
    mode = "smoke" if args.smoke else "default"
    import torch

    torch.set_num_threads(args.threads)
    peak, rows, worktree = 0.0, {}, None
    with tempfile.TemporaryDirectory(prefix="lnf-bench-") as tmp:
        checkouts = {"this checkout": ROOT}
        if args.baseline:
            checkouts["baseline"] = worktree = baseline_worktree(args.baseline, Path(tmp))
        try:  # rounds alternate the checkouts; each figure is the best (least disturbed) of its rounds
            for k in range(args.rounds):
                peak = max(peak, matmul_peak())
                for name, path in checkouts.items():
                    r = measure_in(path, mode, args.threads)
                    print(f"[bench] round {k + 1}/{args.rounds}, {name}: step {1e3 * r['step_seconds']:.1f} ms, "
                          f"decode {r['decode_seconds']:.2f} s", flush=True)
                    best = rows.setdefault(name, r)
                    for key in ("step_seconds", "decode_seconds", "table_decode_seconds"):
                        if key in r:
                            best[key] = min(best[key], r[key])
        finally:
            if args.baseline:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(checkouts["baseline"])],
                               capture_output=True)
    print(f"[bench] float32 GEMM peak {peak / 1e9:.1f} GFLOP/s on {args.threads} threads", flush=True)
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                          text=True).stdout.strip()
    command = "python -m experiments.bench_training" + (" --smoke" if args.smoke else "") + (
        f" --baseline {args.baseline}" if args.baseline else "")
    where = (f"Machine: {cpu_name()}, {os.cpu_count()} cores, {args.threads} torch threads, torch {torch.__version__}. "
             f"Command: `{command}`. Measured {time.strftime('%Y-%m-%d %H:%M %Z')}, best of {args.rounds} alternating "
             f"rounds; GEMM peak {peak / 1e9:.1f} GFLOP/s in the same run; checkout at {head} (+ working tree), "
             f"baseline {args.baseline or 'none'}.\n\n")
    text = where + table(rows, peak)
    print(text)
    out = args.out or ROOT / "outputs" / "studies" / ("bench_training-smoke" if args.smoke else "bench_training")
    from lnf.tempfiles import write_text_atomic

    write_text_atomic(out / "bench_training.json", json.dumps({"peak_flops": peak, "rows": rows,
                                                               "baseline_worktree": worktree and str(worktree)},
                                                              indent=2))
    write_text_atomic(out / "summary.md", text)
    print(f"[bench] wrote {out / 'summary.md'}; collect it with "
          f"`python -m experiments.results_tables --collect bench_training={out}`")


def cpu_name() -> str:
    """The CPU's model name (Linux /proc/cpuinfo), or the platform's processor string."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or platform.machine()


if __name__ == "__main__":
    main()
