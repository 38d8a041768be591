"""Acceptance benchmark: the default pendulum experiment, end to end, plus a 10 000-step energy check.

1. runs ``python -m lnf.train +experiment=pendulum`` (defaults; a fresh data dir, so data generation is
   included) and measures its wall-clock;
2. reads the run's metrics.json (test trajectories, 64×64 grid, all 100 samples);
3. re-loads the checkpoint with ``lnf.load`` and rolls the structure-preserving integrator out for
   10 000 steps (dt = 0.05 s, 200× the training horizon) from test initial conditions: energy_drift;
4. prints every number against its threshold and writes them to ``<run dir>/acceptance.json``.

    python -m experiments.pendulum_acceptance [--skip-train RUN_DIR] [--steps 10000] [--trajectories 4]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]


def run_training(extra: list[str]) -> tuple[Path, float]:
    data_dir = tempfile.mkdtemp(prefix="lnf-acceptance-data-")
    env = {**os.environ, "LNF_DATA_DIR": data_dir}
    before = set((ROOT / "outputs" / "pendulum" / "runs").glob("*"))
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "lnf.train", "+experiment=pendulum", *extra], cwd=ROOT, env=env, check=True)
    seconds = time.perf_counter() - start
    after = set((ROOT / "outputs" / "pendulum" / "runs").glob("*"))
    (run_dir,) = after - before
    return run_dir, seconds


def main() -> None:
    p = argparse.ArgumentParser(prog="python -m experiments.pendulum_acceptance", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--skip-train", type=Path, default=None, help="evaluate an existing run dir instead of training")
    p.add_argument("--steps", type=int, default=10000)
    p.add_argument("--trajectories", type=int, default=4)
    p.add_argument("--dt", type=float, default=0.05)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("overrides", nargs="*", help="extra Hydra overrides for the training run")
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    if args.skip_train:
        run_dir, train_wall = args.skip_train, float("nan")
    else:
        run_dir, train_wall = run_training(args.overrides)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    if np.isnan(train_wall):
        train_wall = metrics.get("total_seconds", float("nan"))

    import lnf
    from lnf.dataset import load_split
    from lnf.evaluation_pipeline import split_long_check
    from lnf.integrators import get_integrator

    model = lnf.load(run_dir / "checkpoints" / "last.ckpt")
    split = load_split(model.checkpoint["data"]["path"], "test")
    run_cfg = json.loads((run_dir / "run.json").read_text())["config"]
    integrator = run_cfg["integrator"]
    long = split_long_check(model, split, args.trajectories, args.steps, integrator, dt=args.dt)
    rows = [
        ("wall-clock of the train command [min] (incl. data generation)", train_wall / 60, "<=", 20.0),
        ("field_rel_l2 median, all 100 samples, 64x64", metrics["field_rel_l2/all/median"], "<=", 0.02),
        ("field_rel_l2 median, extrapolation half", metrics["field_rel_l2/extrapolation/median"], "<=", 0.03),
        ("energy_rel_err (max over test trajectories)", metrics["energy_rel_err/max"], "<=", 0.02),
        (f"energy_drift over {args.steps} steps, {get_integrator(integrator).name} (max)",
         long["energy_drift_long/max"], "<=", 1e-3),
    ]
    print(f"\nmachine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}")
    print(f"run: {run_dir}")
    ok_all = True
    for name, value, op, bound in rows:
        ok = value <= bound
        ok_all &= ok
        print(f"  {'PASS' if ok else 'FAIL'}  {name:70s} {value:10.4g}  (≤ {bound:g})")
    print(f"  other: field_rel_l2 max {metrics['field_rel_l2/all/max']:.4g}, projection_rel_l2 median "
          f"{metrics['projection_rel_l2/all/median']:.4g}, energy_rel_err median {metrics['energy_rel_err/median']:.4g}, "
          f"vpt median {metrics['vpt/median']:.3g} s, rollout {metrics['rollout_seconds_per_trajectory'] * 1e3:.1f} ms/trajectory, "
          f"long rollout {long['energy_drift_long/seconds']:.1f} s")
    out = {"train_wall_seconds": train_wall, **metrics, **long, "passed": bool(ok_all)}
    from lnf.tempfiles import write_text_atomic

    write_text_atomic(run_dir / "acceptance.json", json.dumps(out, indent=2))
    print(f"wrote {run_dir / 'acceptance.json'} (python -m experiments.results_tables --collect "
          f"pendulum_acceptance={run_dir} pendulum_default={run_dir} puts it in the docs)")
    sys.exit(0 if ok_all else 1)


if __name__ == "__main__":
    main()
