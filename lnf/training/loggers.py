"""lnf's loggers: a CSV logger whose resumed run appends to the log it resumes instead of starting a new version,
and a wandb logger without Lightning's deprecated ``anonymous`` argument."""
from __future__ import annotations

import csv
import os
import sys
from pathlib import Path
from typing import Any, Optional

from lightning.fabric.utilities.rank_zero import rank_zero_only
from lightning.pytorch.loggers import CSVLogger as LightningCSVLogger
from lightning.pytorch.loggers import WandbLogger as LightningWandbLogger
from lightning.pytorch.loggers.csv_logs import ExperimentWriter
from omegaconf import OmegaConf


class _AppendingWriter(ExperimentWriter):
    """Lightning's writer deletes an existing ``metrics.csv``; this one keeps it and appends below its header."""

    def _check_log_dir_exists(self) -> None:
        if not os.path.isfile(self.metrics_file_path):
            return
        with open(self.metrics_file_path, newline="") as fh:
            header = next(csv.reader(fh), [])
        self.metrics_keys = sorted(header)


class CSVLogger(LightningCSVLogger):
    """``lightning.pytorch.loggers.CSVLogger`` that, with ``resume=True`` (set by lnf.train when it resumes a
    checkpoint), writes into the newest existing ``version_*`` folder and appends to its ``metrics.csv``:
    one log per run, its history kept across restarts."""

    def __init__(self, save_dir: str, name: Optional[str] = "lightning_logs", version: "int | str | None" = None,
                 resume: bool = False, **kwargs: Any) -> None:
        if resume and version is None:
            root = Path(save_dir) / (name or "")
            versions = [int(p.name[len("version_"):]) for p in root.glob("version_*")
                        if p.is_dir() and p.name[len("version_"):].isdigit()]
            version = max(versions) if versions else None
        super().__init__(save_dir, name=name, version=version, **kwargs)
        self.resume = resume

    @property
    def experiment(self) -> ExperimentWriter:  # type: ignore[override]
        if self._experiment is None and self.resume and rank_zero_only.rank == 0:
            self._fs.makedirs(self.root_dir, exist_ok=True)
            self._experiment = _AppendingWriter(log_dir=self.log_dir)
        return super().experiment


class WandbLogger(LightningWandbLogger):
    """``lightning.pytorch.loggers.WandbLogger`` that passes wandb only the settings it is given: Lightning sends
    ``anonymous=None`` even when it is unset, which wandb ≥ 0.19 answers with a deprecation warning on every run;
    ``settings`` may be a mapping (from the YAML config) of :class:`wandb.Settings` fields, e.g. ``quiet: true``."""

    def __init__(self, *args: Any, anonymous: Optional[bool] = None, settings: Any = None, **kwargs: Any) -> None:
        if settings is not None and not _is_wandb_settings(settings):
            settings = dict(OmegaConf.to_container(settings, resolve=True) if OmegaConf.is_config(settings)
                            else settings)
        if settings is not None:
            kwargs["settings"] = settings
        super().__init__(*args, anonymous=anonymous, **kwargs)
        if anonymous is None:
            self._wandb_init.pop("anonymous", None)


def _is_wandb_settings(value: Any) -> bool:
    return type(value).__name__ == "Settings" and type(value).__module__.startswith("wandb")


def finish_wandb_run() -> None:
    """End this process's wandb run, if one is open: the next job of a Hydra multirun in the same process then
    starts a run of its own (Lightning's WandbLogger otherwise reuses the open run, and every later job logged into
    the first job's run)."""
    wandb = sys.modules.get("wandb")
    if wandb is not None and getattr(wandb, "run", None) is not None:
        wandb.finish()
