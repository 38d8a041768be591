"""Fault injection: kill the training process on purpose, to test that a run survives it."""
from __future__ import annotations

import os
import signal
from typing import Any

import lightning.pytorch as pl


class KillAt(pl.Callback):
    """SIGKILLs this process (no cleanup runs, as when a node dies or the OOM killer strikes) before batch
    `batch` of training epoch `epoch` (``stage="train"``), or before test batch `batch` (``stage="test"``: after
    training ended). Add it with
    ``+callbacks.kill._target_=lnf.training.faults.KillAt +callbacks.kill.epoch=2 +callbacks.kill.batch=1``.
    """

    def __init__(self, epoch: int = 0, batch: int = 0, stage: str = "train") -> None:
        if epoch < 0 or batch < 0:
            raise ValueError(f"KillAt needs epoch ≥ 0 and batch ≥ 0, got epoch {epoch}, batch {batch}")
        if stage not in ("train", "test"):
            raise ValueError(f"KillAt stage must be 'train' or 'test', got {stage!r}")
        self.epoch, self.batch, self.stage = int(epoch), int(batch), stage

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any,
                             batch_idx: int) -> None:
        if self.stage == "train" and trainer.current_epoch == self.epoch and batch_idx == self.batch:
            os.kill(os.getpid(), signal.SIGKILL)

    def on_test_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any,
                            batch_idx: int, dataloader_idx: int = 0) -> None:
        if self.stage == "test" and batch_idx == self.batch:
            os.kill(os.getpid(), signal.SIGKILL)
