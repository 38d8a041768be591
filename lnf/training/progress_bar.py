"""lnf.train's progress bar: Lightning's rich bar with the losses in scientific notation."""
from __future__ import annotations

from typing import Any, Union

from lightning.pytorch.callbacks import RichProgressBar

from lnf.training.console import format_metric


class MetricsProgressBar(RichProgressBar):
    """Lightning's rich progress bar, without the logger's meaningless ``v_num`` and with the losses in
    scientific notation (a loss of 1e-4 read 0.000 before)."""

    def get_metrics(self, trainer: Any, pl_module: Any) -> dict[str, Union[int, str, float, dict[str, float]]]:
        items = super().get_metrics(trainer, pl_module)
        items.pop("v_num", None)
        return {k: format_metric(v) for k, v in items.items()}

    def _get_train_description(self, current_epoch: int) -> str:
        """"Epoch 3/40" counted from 1, as the end-of-run table counts epochs (Lightning's bar says "Epoch 2/39")."""
        text = f"Epoch {current_epoch + 1}" + (f"/{self.trainer.max_epochs}" if self.trainer.max_epochs else "")
        return f"{text:{len(self.validation_description)}}"
