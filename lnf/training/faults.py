"""Fault injection: kill the training process on purpose, to test that a run survives it."""
from __future__ import annotations

import os
import signal
from typing import Any

import lightning.pytorch as pl


class KillAt(pl.Callback):
    """SIGKILLs this process before training batch `batch` of epoch `epoch` (no cleanup runs, as when a
    node dies or the OOM killer strikes). Add it with
    ``+callbacks.kill._target_=lnf.training.faults.KillAt +callbacks.kill.epoch=2 +callbacks.kill.batch=1``.
    """

    def __init__(self, epoch: int, batch: int = 0) -> None:
        if epoch < 0 or batch < 0:
            raise ValueError(f"KillAt needs epoch ≥ 0 and batch ≥ 0, got epoch {epoch}, batch {batch}")
        self.epoch, self.batch = int(epoch), int(batch)

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any,
                             batch_idx: int) -> None:
        if trainer.current_epoch == self.epoch and batch_idx == self.batch:
            os.kill(os.getpid(), signal.SIGKILL)
