"""Each scene's default run, whole, against a baseline commit's default run measured in the same session.

    python -m experiments.bench_defaults                                  # the pendulum, this checkout alone
    python -m experiments.bench_defaults --baseline bcb7020               # + that commit's defaults, same machine
    python -m experiments.bench_defaults --scenes pendulum bump --baseline bcb7020
    python -m experiments.bench_defaults --smoke                          # tiny settings (the test suite)

For every scene and checkout, one after the other (never two at once): ``python -m lnf.train
+experiment=<scene>`` with the checkout first on ``PYTHONPATH`` (a baseline is checked out with ``git worktree``
into a temporary folder), timed as a whole process; then ``python -m lnf.evaluate`` of its final checkpoint on
``--points`` points drawn uniformly over the scene's box (initial fields observed on those points, fields scored
on them): the "any points" check beside the run's own test grid. Both checkouts read one data folder, so a
dataset both generate with the same settings is made once (its generation is then in the first run's time only;
the table's `data+training` column says so).

Prints a Markdown table, with this checkout's time and errors as ratios to the baseline's, and writes it with
its provenance as ``summary.md``, beside the raw ``bench_defaults.json`` and each run's folder, into
``outputs/studies/bench_defaults/`` (or ``--out DIR``), atomically. A run whose folder already holds a
``metrics.json`` of the same commit is reused with ``--reuse`` (a changed working tree is not detected); the
table says when each run was measured.
The budget of every run is its epochs, so the errors do not depend on the machine's speed; the times do:
run this alone on the machine (the load average before each run is recorded).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Optional

from experiments.bench_training import baseline_worktree, cpu_name
from experiments.studylib import SMOKE_DATA, SMOKE_NEURAL
from lnf.tempfiles import write_text_atomic

ROOT = Path(__file__).resolve().parent.parent

SMOKE = [*SMOKE_DATA, *SMOKE_NEURAL, "evaluation.long_steps=0", "evaluation.every_n_epochs=0"]
COMMON = ["logger=csv", "evaluation.figures=0", "trainer.enable_progress_bar=false"]
KEYS = {  # column → metrics.json key of the run (grid) or of the evaluation on scattered points
    "grid": "field_rel_l2/all/median",
    "extrapolation": "field_rel_l2/extrapolation/median",
    "max": "field_rel_l2/all/max",
    "energy": "energy_rel_err/max",
    "diverged": "diverged_count",
}


def _commit(checkout: Path) -> str:
    out = subprocess.run(["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"], capture_output=True,
                         text=True)
    dirty = subprocess.run(["git", "-C", str(checkout), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return out.stdout.strip() + (" (+ working tree)" if dirty else "")


# Runs an entry point (argv[1], e.g. lnf.train) of the checkout on PYTHONPATH with that checkout's conf/ as
# lnf.conf, registered before lnf is imported: an older lnf beside an editable install would otherwise compose the
# installed checkout's configs (lnf/__init__.py maps its own since the bench was written).
BOOTSTRAP = ("import sys, runpy, importlib.util as u\n"
             "init = sys.argv.pop(1)\n"
             "spec = u.spec_from_file_location('lnf.conf', init, submodule_search_locations=[init.rsplit('/', 1)[0]])\n"
             "module = u.module_from_spec(spec); sys.modules['lnf.conf'] = module; spec.loader.exec_module(module)\n"
             "entry = sys.argv.pop(1)\n"
             "runpy.run_module(entry, run_name='__main__', alter_sys=True)\n")


def _run(cmd: list[str], checkout: Path, log: Path, threads: int) -> float:
    """Run the entry point `cmd` = [module, *overrides] in `checkout` (first on PYTHONPATH, its own conf/); its
    wall time [s]. A failure names its log."""
    cmd = [sys.executable, "-c", BOOTSTRAP, str(checkout / "conf" / "__init__.py"), *cmd]
    env = {**os.environ, "PYTHONPATH": str(checkout), "HYDRA_FULL_ERROR": "1", "OMP_NUM_THREADS": str(threads)}
    env.pop("LNF_ROOT", None)
    log.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with open(log, "w") as fh:
        rc = subprocess.run(cmd, cwd=str(checkout), env=env, stdout=fh, stderr=subprocess.STDOUT).returncode
    seconds = time.perf_counter() - start
    if rc != 0:
        tail = "".join(log.read_text(errors="replace").splitlines(keepends=True)[-15:])
        raise SystemExit(f"[bench] {' '.join(cmd[4:6])} failed (exit {rc}) in {checkout}; its log: {log}\n{tail}")
    return seconds


def measure(scene: str, name: str, checkout: Path, out: Path, args: argparse.Namespace) -> dict[str, Any]:
    """Train the scene's default in `checkout`, then evaluate its checkpoint on scattered points."""
    run = out / f"{scene}-{name}"
    record = run / "bench.json"
    commit = _commit(checkout)
    if args.reuse and record.is_file() and (run / "metrics.json").is_file():
        old = json.loads(record.read_text())
        if old.get("commit") == commit:
            print(f"[bench] {scene}, {name}: reusing {run} (measured {old['measured']})", flush=True)
            return old
    if run.exists():
        shutil.rmtree(run)
    extra = (SMOKE if args.smoke else []) + list(args.override)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"[bench] {scene}, {name} ({commit}): training (load average {load:.2f}) ...", flush=True)
    measured = time.strftime("%Y-%m-%d %H:%M %Z")
    wall = _run(["lnf.train", f"+experiment={scene}", *COMMON, f"threads={args.threads}",
                      f"hydra.run.dir={run}", f"paths.data_dir={out / 'data'}", *extra],
                checkout, run / "train.out", args.threads)
    metrics = json.loads((run / "metrics.json").read_text())
    print(f"[bench] {scene}, {name}: {wall / 60:.1f} min, field error {metrics.get(KEYS['grid'], float('nan')):.4f}; "
          f"scattered points ...", flush=True)
    ev = run / "scattered"
    _run(["lnf.evaluate", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}", "grid.kind=random",
               f"grid.n_points={args.points}", "grid.seed=1", "figures=0", f"threads={args.threads}",
               f"hydra.run.dir={ev}"], checkout, ev / "evaluate.out", args.threads)
    scattered = json.loads((ev / "metrics.json").read_text())
    row = {"scene": scene, "checkout": name, "commit": commit, "measured": measured, "load_before": load,
           "wall_seconds": wall, "train_seconds": metrics.get("train_seconds"),
           "epochs_run": metrics.get("epochs_run"), "max_epochs": metrics.get("max_epochs"),
           "stopped_early": bool(metrics.get("stopped_early") or metrics.get("stopped_by_time_limit")),
           **{k: metrics.get(v) for k, v in KEYS.items()},
           "scattered": scattered.get(KEYS["grid"]), "scattered_diverged": scattered.get(KEYS["diverged"]),
           "points": args.points}
    write_text_atomic(record, json.dumps(row, indent=1))
    return row


def _f(value: Any, spec: str = ".4f") -> str:
    return "—" if value is None else format(value, spec)


def table(rows: list[dict[str, Any]]) -> str:
    head = ("| scene | checkout | whole run [min] | data+training [min] | epochs | field error, test grid | "
            "on scattered points (× grid) | extrapolation | max | energy error, max | diverged |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        ratio = r["scattered"] / r["grid"] if r["scattered"] and r["grid"] else None
        epochs = f"{r['epochs_run']:.0f} of {r['max_epochs']:.0f}" + (" (stopped early)" if r["stopped_early"] else "")
        lines.append(f"| {r['scene']} | {r['checkout']} ({r['commit']}) | {r['wall_seconds'] / 60:.1f} | "
                     f"{r['train_seconds'] / 60:.1f} | {epochs} | {_f(r['grid'])} | {_f(r['scattered'])} "
                     f"({_f(ratio, '.2f')}) | {_f(r['extrapolation'])} | {_f(r['max'])} | {_f(r['energy'])} | "
                     f"{r['diverged']:.0f} + {r['scattered_diverged']:.0f} |")
    text = head + "\n".join(lines) + "\n"
    ratios = []
    for scene in dict.fromkeys(r["scene"] for r in rows):
        by = {r["checkout"]: r for r in rows if r["scene"] == scene}
        if "this checkout" in by and "baseline" in by:
            a, b = by["this checkout"], by["baseline"]
            ratios.append(f"{scene}: whole run × {a['wall_seconds'] / b['wall_seconds']:.2f}, field error × "
                          f"{a['grid'] / b['grid']:.2f} on the test grid and × {a['scattered'] / b['scattered']:.2f} "
                          f"on scattered points, extrapolation × {a['extrapolation'] / b['extrapolation']:.2f}")
    if ratios:
        text += "\nThis checkout against the baseline: " + "; ".join(ratios) + ".\n"
    return text


def main(argv: Optional[list[str]] = None) -> None:
    p = argparse.ArgumentParser(prog="python -m experiments.bench_defaults", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=["pendulum"], help="experiment configs (conf/experiment/)")
    p.add_argument("--baseline", default=None, metavar="REV", help="a commit whose defaults are measured too")
    p.add_argument("--points", type=int, default=4096, help="scattered points of the any-points check")
    p.add_argument("--threads", type=int, default=2, help="torch threads per run")
    p.add_argument("--override", nargs="*", default=[], metavar="KEY=VALUE",
                   help="extra Hydra overrides of every run (both checkouts)")
    p.add_argument("--smoke", action="store_true", help="tiny settings (the test suite)")
    p.add_argument("--reuse", action="store_true", help="reuse a run of the same commit found in the output folder")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    for scene in args.scenes:
        if not (ROOT / "conf" / "experiment" / f"{scene}.yaml").is_file():
            p.error(f"--scenes {scene}: no conf/experiment/{scene}.yaml")
    out = (args.out or ROOT / "outputs" / "studies" / ("bench_defaults-smoke" if args.smoke else "bench_defaults"))
    out = out.expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    worktree = None
    with tempfile.TemporaryDirectory(prefix="lnf-bench-") as tmp:
        checkouts = {"this checkout": ROOT}
        if args.baseline:
            worktree = baseline_worktree(args.baseline, Path(tmp))
            checkouts = {"baseline": worktree, **checkouts}
        try:
            for scene in args.scenes:
                for name, path in checkouts.items():
                    rows.append(measure(scene, name, path, out, args))
        finally:
            if args.baseline:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(checkouts["baseline"])],
                               capture_output=True)
    command = "python -m experiments.bench_defaults --scenes " + " ".join(args.scenes) + (
        f" --baseline {args.baseline}" if args.baseline else "") + (" --smoke" if args.smoke else "") + (
        " --override " + " ".join(args.override) if args.override else "")
    import torch

    when = ", ".join(sorted({r["measured"] for r in rows}))
    loads = ", ".join(f"{r['load_before']:.2f}" for r in rows)
    where = (f"Machine: {cpu_name()}, {os.cpu_count()} cores, {args.threads} torch threads, torch "
             f"{torch.__version__}. Command: `{command}`. Measured {when}, one run at a time; load average before "
             f"each run {loads}. Field errors: relative L² over all "
             f"test frames, median over trajectories; scattered: {args.points} points uniform over the box; "
             f"diverged: test rollouts on the grid + on the scattered points.\n\n")
    text = where + table(rows)
    print(text)
    write_text_atomic(out / "bench_defaults.json", json.dumps({"rows": rows,
                                                               "baseline_worktree": worktree and str(worktree)},
                                                              indent=1))
    write_text_atomic(out / "summary.md", text)
    print(f"[bench] wrote {out / 'summary.md'}")


if __name__ == "__main__":
    main()
