"""LightningModule: the Lagrangian neural field, its two losses, and the optimiser."""
from __future__ import annotations

import functools
import math
from typing import Any, Optional

import lightning.pytorch as pl
import torch
from torch import Tensor

from lnf.model import build_model
from lnf.training.batch import SnapshotBatch
from lnf.utils import check_numbers


class LNFModule(pl.LightningModule):
    """Trains φ and ρ̃ with ℓ = ℓ^r + ℓ^p (docs/method.md §4); wraps closed-form baselines (POD, full order) too.

    All arguments are plain dicts so that the checkpoint describes itself (``save_hyperparameters``).

    Args:
        scene, model, quadrature: ``_target_`` specs of the scene, the LagrangianNeuralField (its other
            arguments) and the quadrature rule of the reduced dynamics.
        optimizer: ``lr`` (field), ``step_size_lr`` (log α), ``weight_decay``, ``warmup_steps``,
            ``schedule`` ('cosine' or 'constant'), ``min_lr_ratio``, ``energy_warmup_epochs`` (see
            :meth:`energy_factor`).
        data: the data settings the model was trained on (kept for re-evaluation).
    """

    def __init__(self, scene: dict[str, Any], model: dict[str, Any], quadrature: dict[str, Any],
                 optimizer: Optional[dict[str, Any]] = None, data: Optional[dict[str, Any]] = None) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.model = build_model(scene, model, quadrature)
        self.optimizer_cfg = {"lr": 3e-4, "step_size_lr": 1e-2, "weight_decay": 0.0, "warmup_steps": 0,
                              "schedule": "cosine", "min_lr_ratio": 0.0, "energy_warmup_epochs": 0,
                              **(optimizer or {})}
        check_numbers(self.optimizer_cfg, prefix="optimizer.")  # NaN, inf, lr ≤ 0, … named before any step
        self.restored_fit_metrics: dict[str, float] = {}

    def fit_metrics(self) -> dict[str, float]:
        """The latest epoch-level training and validation values (``train/*``, ``val/*``, no per-step ones)."""
        if self._trainer is None:
            return {}
        return {k: float(v) for k, v in self.trainer.callback_metrics.items()
                if k.startswith(("train/", "val/")) and not k.endswith("_step")}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # a run resumed after its last epoch (killed in the test phase) trains no more: it reports these
        checkpoint["lnf_fit_metrics"] = {**self.restored_fit_metrics, **self.fit_metrics()}

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        self.restored_fit_metrics = dict(checkpoint.get("lnf_fit_metrics") or {})

    def _step(self, batch: SnapshotBatch, stage: str, batch_idx: int = 0) -> Tensor:
        out = self.model.losses(batch.points, batch.values, batch.velocities, batch.potential,
                                energy_factor=self.energy_factor(), gradients=batch.gradients,
                                accelerations=batch.accelerations, acceleration_valid=batch.acceleration_valid)
        if stage == "train" and hasattr(self.model, "track_code_range"):
            # the box of a tabulated dynamics: the codes of the current epoch (restarted with its first batch)
            self.model.track_code_range(out["codes"], reset=batch_idx == 0)
        bs = len(batch)
        # epoch values are averaged over DDP ranks (each holds part of the global batch)
        log = functools.partial(self.log, batch_size=bs, on_step=stage == "train", on_epoch=True, sync_dist=True)
        log(f"{stage}/loss", out["loss"], prog_bar=True)
        for key in ("reconstruction", "projection", "velocity", "energy", "dynamics", "gradient", "mass_condition"):
            if key in out:
                log(f"{stage}/{key}", out[key])
        if stage == "train":
            self.log("train/step_size", self.model.step_size.detach(), batch_size=bs, on_step=True, on_epoch=False)
        return out["loss"]

    def energy_factor(self, epoch: Optional[int] = None) -> float:
        """Schedule of the energy loss at `epoch` (default the current one): off for the first
        w = ``energy_warmup_epochs`` epochs (the field first learns the values), then ramped linearly to 1
        over the next w."""
        epoch = self.current_epoch if epoch is None else epoch
        w = int(self.optimizer_cfg["energy_warmup_epochs"])
        if w <= 0:
            return 1.0
        return float(min(max((epoch - w + 1) / w, 0.0), 1.0))

    def training_step(self, batch: SnapshotBatch, batch_idx: int) -> Tensor:
        loss = self._step(batch, "train", batch_idx)
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"training loss became {loss.item()} at step {self.global_step}; lower optimizer.lr "
                f"(now {self.optimizer_cfg['lr']}) or model.step_size")
        return loss

    def validation_step(self, batch: SnapshotBatch, batch_idx: int) -> Optional[Tensor]:
        return self._step(batch, "val") if self.model.trainable else None

    def test_step(self, batch: SnapshotBatch, batch_idx: int) -> Optional[Tensor]:
        # closed-form baselines have no training loss; their test metrics come from the evaluation callback
        return self._step(batch, "test") if self.model.trainable else None

    def configure_optimizers(self) -> dict[str, Any]:
        cfg = self.optimizer_cfg
        field_params = list(self.model.field.parameters())
        opt = torch.optim.Adam([
            {"params": field_params, "lr": cfg["lr"], "weight_decay": cfg["weight_decay"]},
            {"params": [self.model.log_step_size], "lr": cfg["step_size_lr"], "weight_decay": 0.0},
        ])
        total = max(int(self.trainer.estimated_stepping_batches), 1)
        warmup = int(cfg["warmup_steps"])
        floor = float(cfg["min_lr_ratio"])
        schedule = cfg["schedule"]
        if schedule not in ("cosine", "constant"):
            raise ValueError(f"optimizer.schedule must be 'cosine' or 'constant', got {schedule!r}")

        def factor(step: int) -> float:
            if step < warmup:
                return (step + 1) / warmup
            if schedule == "constant":
                return 1.0
            progress = min((step - warmup) / max(total - warmup, 1), 1.0)
            return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * progress))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}
