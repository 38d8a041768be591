"""Composing configs in tests (Hydra's compose API) with tiny data and a temporary output dir."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

from lnf.integrators import RK4

CONF = str(Path(__file__).resolve().parents[1] / "conf")

TINY = ["data.n_train=3", "data.n_val=1", "data.n_test=2", "data.n_times=20", "data.train_times=10",
        "data.fine_resolution=12", "data.coarse_resolution=8", "data.batch_size=8", "model.width=16",
        "model.hyper_width=8", "evaluation.long_steps=20", "evaluation.long_trajectories=1",
        "evaluation.every_n_epochs=1", "evaluation.val_trajectories=1", "evaluation.val_resolution=8",
        "evaluation.figures=1", "evaluation.max_reduction_points=64", "quadrature.order=4",
        "evaluation.closure_shooting_iterations=1"]
# for runs whose tests read only checkpoints, files and metrics.json: no figure, validation rollout or long-horizon
# check (a run compared with another gets the same overrides)
METRICS_ONLY = ["evaluation.figures=0", "evaluation.every_n_epochs=0", "evaluation.long_steps=0"]


def compose_config(name: str, overrides: list[str], tmp_path: Path) -> DictConfig:
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(name, overrides=overrides, return_hydra_config=True)
    with open_dict(cfg):
        cfg.paths.output_dir = str(tmp_path / "out")
        cfg.paths.data_dir = str(tmp_path / "data")
        cfg.hydra.runtime.output_dir = str(tmp_path / "out")
    HydraConfig.instance().set_config(cfg)
    return cfg


ROOT = Path(__file__).resolve().parents[1]
TIMING = ("seconds",)  # metrics that measure time, not results


def run_cli(args: list[str], root: Path, check: bool = True, timeout: int = 600) -> subprocess.CompletedProcess:
    """`python -m lnf.train *args` from the repository root, outputs and data under `root` (LNF_ROOT)."""
    env = {**os.environ, "LNF_ROOT": str(root), "WANDB_MODE": "offline", "WANDB_SILENT": "true"}
    proc = subprocess.run([sys.executable, "-m", "lnf.train", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)
    if check:
        assert proc.returncode == 0, f"exit {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
    return proc


def result_metrics(metrics: dict) -> dict:
    """The metrics that a deterministic rerun must reproduce: no timings, and no measured errors of the evaluation's
    tables (``*table_error``: interpolation error at the level of float32 rounding, which differs between runs whose
    weights differ in the last bits, such as DDP and one process)."""
    return {k: v for k, v in metrics.items() if not any(t in k for t in TIMING) and not k.endswith("table_error")}


class DivergesAtStep(RK4):
    """RK4 that marks trajectory `which` as diverged at step `step` (through the integrator's own check)."""

    def __init__(self, step: int, which: int = 1) -> None:
        super().__init__()
        self.at, self.which, self.calls = step, which, 0

    def _bad(self, *xs):
        self.calls += 1
        bad = super()._bad(*xs)
        if self.calls == self.at:
            bad[self.which] = True
        return bad


def split_stand_in(**arrays) -> SimpleNamespace:
    """A stand-in for a :class:`lnf.dataset.TrajectorySplit` holding `arrays`, with its ``loads(scene)``."""
    from lnf.dataset import TrajectorySplit

    split = SimpleNamespace(**arrays)
    split.loads = lambda scene: TrajectorySplit.loads(split, scene)
    return split
