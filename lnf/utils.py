"""Small helpers shared by the entry points: config checks, run metadata, the summary table."""
from __future__ import annotations

import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import Any, Optional

from omegaconf import DictConfig, OmegaConf

SUMMARY_KEYS = [
    "field_rel_l2/all/median", "field_rel_l2/in_horizon/median", "field_rel_l2/extrapolation/median",
    "field_rel_l2/all/max", "projection_rel_l2/all/median", "latent_rmse/median", "energy_rel_err/max",
    "energy_drift/max", "energy_drift_long/max", "vpt/median", "rollout_seconds_per_trajectory",
    "rollout_seconds_per_step", "fields_seconds_per_trajectory", "train_seconds", "total_seconds",
]


def check_config(cfg: DictConfig) -> None:
    """Clear errors for settings that would otherwise fail deep inside torch."""
    model = cfg.model
    if model.get("latent_dim") is not None and int(model.latent_dim) < 1:
        raise ValueError(f"model.latent_dim must be ≥ 1, got {model.latent_dim}")
    if model.get("reduction_steps") is not None and int(model.reduction_steps) < 1:
        raise ValueError(f"model.reduction_steps (K) must be ≥ 1, got {model.reduction_steps}")
    dynamics = cfg.get("dynamics")
    if dynamics is not None and not str(dynamics.get("_target_", "")).endswith("ReducedDynamics") \
            and not str(model.get("_target_", "")).endswith("LagrangianNeuralField"):
        raise ValueError(f"dynamics={dynamics._target_} (learned or tabulated latent dynamics) needs model=lnf "
                         f"(a neural field with codes to learn or tabulate on), got model={model.get('_target_')}; "
                         f"use dynamics=lagrangian with this model")
    missing = {f"{k}.{m}" for k, v in cfg.items() if k != "hydra" and OmegaConf.is_config(v)
               for m in OmegaConf.missing_keys(v)}
    if missing:
        raise ValueError(f"missing required config values: {sorted(missing)}")


def resolved_config(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config as plain containers, without Hydra's own `hydra` node (present under compose)."""
    return {k: OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v
            for k, v in cfg.items() if k != "hydra"}


def run_metadata(cfg: DictConfig) -> dict[str, Any]:
    """Package versions, git commit (and whether the tree had uncommitted changes), command line and the
    resolved config of a run."""
    versions = {}
    for pkg in ["lnf", "torch", "lightning", "hydra-core", "omegaconf", "wandb", "h5py", "numpy", "scipy", "torchdiffeq"]:
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    here = Path(__file__).resolve().parent
    commit = _git(["rev-parse", "HEAD"], here)
    status = _git(["status", "--porcelain", "--untracked-files=no"], here) if commit else None
    return {"versions": versions, "git_commit": commit or None,
            "git_dirty": None if status is None else bool(status), "argv": sys.argv,
            "python": sys.version, "platform": platform.platform(), "config": resolved_config(cfg)}


def _git(args: list[str], cwd: Path) -> Optional[str]:
    """stdout of `git args` in `cwd`, or None when git or the repository is not there."""
    try:
        proc = subprocess.run(["git", *args], capture_output=True, text=True, timeout=5, cwd=str(cwd))
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


def summary_rows(metrics: dict[str, float]) -> list[tuple[str, str]]:
    """The rows of :func:`print_summary`: the headline metrics of :data:`SUMMARY_KEYS` (4 significant digits), and
    after a training the epochs run of the budget, and what stopped it early if anything did."""
    rows = [(k, f"{metrics[k]:.4g}") for k in SUMMARY_KEYS if k in metrics]
    if metrics.get("max_epochs"):
        rows.append(("epochs_run", f"{int(metrics.get('epochs_run', 0))} of {int(metrics['max_epochs'])}"))
        if metrics.get("stopped_by_time_limit"):
            rows.append(("stopped_by", "the time limit (trainer.max_time)"))
        elif metrics.get("stopped_early"):
            rows.append(("stopped_by", "a callback (early stopping)"))
    return rows


def print_summary(metrics: dict[str, float], title: str = "test metrics", caption: Optional[str] = None) -> None:
    """A short table of the headline metrics (rich if available), with `caption` in words below it."""
    rows = summary_rows(metrics)
    try:
        from rich.console import Console
        from rich.table import Table

        table = Table(title=title, caption=caption, caption_justify="left")
        table.add_column("metric")
        table.add_column("value", justify="right")
        for k, v in rows:
            table.add_row(k, v)
        Console().print(table)
    except ImportError:  # pragma: no cover
        print(title)
        for k, v in rows:
            print(f"  {k:40s} {v}")
        if caption:
            print(caption)
