"""What lnf.train reports of a run besides its metrics: the training budget that ran (and what stopped it early), the
run record of run.json, the loggers and progress bar it sets up, and where its wandb runs are."""
from __future__ import annotations

import inspect
import json
import logging
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import hydra
import lightning.pytorch as pl
import torch
from lightning.pytorch.callbacks import EarlyStopping, ProgressBar, Timer
from omegaconf import DictConfig

from lnf.baselines.latent_mlp import latent_trajectories
from lnf.training.progress_bar import MetricsProgressBar
from lnf.utils import run_metadata

log = logging.getLogger("lnf.train")


def fit_latent_dynamics(model: Any, datamodule: Any) -> dict[str, float]:
    """Fit the black-box latent dynamics to the codes of the training trajectories (after the field)."""
    points, values, velocities = (torch.as_tensor(a) for a in datamodule.observations("train"))
    model.eval()
    q, v = latent_trajectories(model, points, values, velocities)
    with torch.enable_grad():
        info = model.latent_dynamics.fit(q, v, datamodule.dt)
    log.info("latent dynamics fitted in %.1f s (loss %.3e)", info["latent_fit_seconds"], info["latent_fit_loss"])
    return info


def build_loggers(cfg: DictConfig, output_dir: Path, resume: bool = False) -> list[Any]:
    """The configured loggers; a logger that takes ``resume`` (lnf's CSVLogger) appends to its log when resuming."""
    loggers = []
    for name, spec in (cfg.get("logger") or {}).items():
        if spec is None:
            continue
        if "save_dir" in spec:
            Path(spec.save_dir).mkdir(parents=True, exist_ok=True)
        cls = hydra.utils.get_class(spec._target_)
        kwargs = {"resume": resume} if "resume" in inspect.signature(cls).parameters else {}
        loggers.append(hydra.utils.instantiate(spec, **kwargs))
    return loggers


def progress_bar(cfg: DictConfig, callbacks: list[Any]) -> list[Any]:
    """lnf's progress bar (losses in scientific notation, no ``v_num``) unless the bar is off or one is configured."""
    if not cfg.trainer.get("enable_progress_bar", True) or any(isinstance(c, ProgressBar) for c in callbacks):
        return []
    return [MetricsProgressBar()]


def training_budget(trainer: pl.Trainer, trained: bool) -> dict[str, float]:
    """Epochs and optimiser steps run, the epoch budget, and whether ``trainer.max_time`` (`stopped_by_time_limit`)
    or anything else, such as an EarlyStopping callback (`stopped_early`), ended training before the budget."""
    max_epochs = int(trainer.max_epochs or 0)
    if not trained:
        return {"epochs_run": 0.0, "max_epochs": float(max_epochs), "global_steps": 0.0, "stopped_by_time_limit": 0.0,
                "stopped_early": 0.0}
    epochs = int(trainer.fit_loop.epoch_progress.current.completed)
    timer = next((c for c in trainer.callbacks if isinstance(c, Timer)), None)
    stopped = timer is not None and epochs < max_epochs and (timer.time_remaining("train") or 0.0) <= 0
    return {"epochs_run": float(epochs), "max_epochs": float(max_epochs), "global_steps": float(trainer.global_step),
            "stopped_by_time_limit": float(stopped), "stopped_early": float(epochs < max_epochs and not stopped)}


def stop_reason(trainer: pl.Trainer) -> str:
    """What ended training before its epoch budget when no time limit did: an EarlyStopping callback (and what it
    watched), or another callback that set ``trainer.should_stop``."""
    for cb in trainer.callbacks:
        if isinstance(cb, EarlyStopping) and cb.stopped_epoch > 0:
            return f"early stopping on {cb.monitor} (EarlyStopping, patience {cb.patience})"
    return "a callback that set trainer.should_stop"


def budget_sentence(metrics: dict[str, float], max_time: Any, trained: bool, reason: str = "") -> str:
    """The end-of-run line that says in words whether the whole epoch budget ran, and if not what stopped it."""
    if not trained:
        return "training: none (the model is fitted in closed form)"
    done, total, steps = int(metrics["epochs_run"]), int(metrics["max_epochs"]), int(metrics["global_steps"])
    if metrics.get("stopped_by_time_limit"):
        return (f"training: STOPPED by the time limit trainer.max_time={max_time} after {done} of {total} epochs "
                f"({steps} steps): these results are not those of the full budget; raise or remove "
                f"trainer.max_time and resume with the same command")
    if metrics.get("stopped_early"):
        return (f"training: STOPPED early after {done} of {total} epochs ({steps} steps) by "
                f"{reason or 'a callback that set trainer.should_stop'}")
    return f"training: all {total} epochs ran ({steps} steps); no time limit stopped it"


def run_record(cfg: DictConfig, path: Path) -> dict[str, Any]:
    """run.json's contents: this run's metadata, with the metadata of the earlier runs in the same output dir
    (a resumed run) kept under ``previous_runs``, oldest first."""
    meta = {**run_metadata(cfg), "started_at": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return meta
    if isinstance(old, dict):
        meta["previous_runs"] = [*old.pop("previous_runs", []), old]
    return meta


def wandb_hints(trainer: pl.Trainer) -> list[str]:
    """One line per wandb run saying where it is (wandb itself is silent, see conf/logger/wandb.yaml): an offline
    run's folder and how to upload it, an online run's address."""
    lines = []
    for logger in trainer.loggers:
        if type(logger).__name__ != "WandbLogger" or getattr(logger, "_experiment", None) is None:
            continue
        run = logger.experiment
        settings = getattr(run, "settings", None)
        if getattr(settings, "_offline", False) and getattr(settings, "sync_dir", None):
            lines.append(f"wandb: offline run; upload it with `wandb sync {settings.sync_dir}`")
        elif getattr(run, "url", None):
            lines.append(f"wandb: run at {run.url}")
    return lines
