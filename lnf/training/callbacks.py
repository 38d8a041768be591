"""Evaluation callback: reduced rollouts, energy checks and Figure 3, apart from the LightningModule."""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any, Optional

import lightning.pytorch as pl
import torch

from lnf.evaluation import reduction_subset
from lnf.evaluation_pipeline import (EvaluationData, EvaluationReport, EvaluationSpec, evaluate_model,
                                     write_report)
from lnf.integrators import Integrator, get_integrator
from lnf.quadrature import midpoint_grid
from lnf.utils import require

log = logging.getLogger("lnf.evaluation")


class RolloutEvaluationCallback(pl.Callback):
    """Rolls out the reduced dynamics on held-out trajectories and logs docs/method.md §7.3 metrics.

    Runs on the validation split every `every_n_epochs` validation epochs (on `val_trajectories`
    trajectories and a `val_resolution`² grid) and on the test split at test time (all test
    trajectories, the stored fine grid), where it also runs the long-horizon energy check, draws
    Figure 3 to PNG and wandb, and writes ``metrics.json``.

    Args:
        integrator: integrator object or spec for the rollouts.
        output_dir: where figures/ and metrics.json go.
        every_n_epochs: validation rollouts every this many validation epochs (0 disables them).
        val_trajectories: how many validation trajectories to roll out.
        val_resolution: evaluation grid per axis during validation.
        long_steps, long_trajectories, long_dt: the long-horizon energy check at test (0 steps disables).
        figures: how many test trajectories get a Figure 3.
        max_reduction_points: ρ̃ of the true fields uses an evenly strided subset of at most this many
            evaluation points (decoding and errors use all of them).
        decoding: ``auto`` | ``exact`` | ``tabulated``: how test and validation frames are decoded
            (:func:`lnf.evaluation.evaluate_rollouts`).
        closure_shooting_iterations: the budget of the closure's shooting search after training (Levenberg–Marquardt
            iterations per closure term in each stage; 0: the residual fit alone), see
            :func:`lnf.closure_choice.shoot_closure`.
    """

    def __init__(self, integrator: "Integrator | dict | str" = "implicit_midpoint", output_dir: str = ".",
                 every_n_epochs: int = 5, val_trajectories: int = 4, val_resolution: int = 32,
                 long_steps: int = 10000, long_trajectories: int = 4, long_dt: float = 0.05,
                 figures: int = 2, max_reduction_points: Optional[int] = 1024, decoding: str = "auto",
                 closure_shooting_iterations: int = EvaluationSpec.closure_shooting_iterations) -> None:
        super().__init__()
        try:
            self.integrator = get_integrator(integrator)
        except (TypeError, ValueError, KeyError) as err:
            raise ValueError(f"integrator={integrator!r}: {err}") from err
        self.output_dir = Path(output_dir)
        self.every_n_epochs = require("evaluation.every_n_epochs", every_n_epochs)
        self.val_trajectories = require("evaluation.val_trajectories", val_trajectories)
        self.val_resolution = require("evaluation.val_resolution", val_resolution)
        self.spec = EvaluationSpec(integrator=self.integrator, split="test", max_reduction_points=max_reduction_points,
                                   decoding=decoding, long_steps=long_steps, long_trajectories=long_trajectories,
                                   long_dt=long_dt, figures=figures,
                                   closure_shooting_iterations=closure_shooting_iterations)
        self.report: Optional[EvaluationReport] = None
        self._val_count = 0

    def state_dict(self) -> dict[str, Any]:  # saved in checkpoints: a resumed run rolls out at the same epochs
        return {"val_count": self._val_count}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._val_count = int(state_dict.get("val_count", 0))

    @property
    def test_metrics(self) -> dict[str, float]:
        """The metrics of the last test evaluation (empty before it)."""
        return {} if self.report is None else self.report.metrics

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking or self.every_n_epochs <= 0:
            return
        latent = getattr(pl_module.model, "latent_dynamics", None)
        if latent is not None and not bool(latent.fitted):
            return  # black-box dynamics are fitted after the field: nothing to roll out yet
        self._val_count += 1
        if self._val_count % self.every_n_epochs:
            return
        split = trainer.datamodule.split("val")
        n = min(self.val_trajectories, len(split))
        scene = pl_module.model.scene
        if split.from_arrays or split.states.shape[-1] == 0 or not scene.provides("fields"):
            # the stored fields on (a strided subset of at most val_resolution^dim_B of) the stored points
            sub = reduction_subset(len(split.fine_points), None, self.val_resolution ** scene.body_dim)
            data = EvaluationData.of_split(split, scene, n, subset=sub)
        else:  # the scene's fields on a midpoint grid
            data = dataclasses.replace(EvaluationData.of_split(split, scene, n), true_fields=None, true_velocities=None,
                                       points=midpoint_grid(self.val_resolution, scene.bounds).numpy())
        spec = EvaluationSpec(integrator=self.integrator, decoding=self.spec.decoding,
                              label=f"validation rollout (epoch {trainer.current_epoch})")
        with torch.inference_mode(False), torch.no_grad():
            metrics = evaluate_model(pl_module.model, data, spec).metrics
        keys = ["field_rel_l2/all/median", "field_rel_l2/extrapolation/median", "projection_rel_l2/all/median",
                "energy_rel_err/max", "latent_rmse/median", "vpt/median"]
        for key in keys:
            pl_module.log(f"val/{key}", metrics[key], sync_dist=True)

    def on_test_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        model = pl_module.model
        split = trainer.datamodule.split("test")
        data = EvaluationData.of_split(split, model.scene)  # on the fine points' grid (of_split finds it)
        with torch.inference_mode(False), torch.no_grad():
            self.report = evaluate_model(model, data, self.spec)
        for key, value in self.report.metrics.items():  # equal on every rank (each evaluates the whole split)
            pl_module.log(f"test/{key}", float(value), sync_dist=True)

    def write_results(self, trainer: pl.Trainer, metrics: dict[str, float]) -> list[Path]:
        """metrics.json (the test metrics and the run's own `metrics`) and Figure 3 of the last test evaluation (PNG
        and wandb), on rank 0, after last.ckpt is written (:func:`lnf.evaluation_pipeline.write_report`: a figure
        that cannot be drawn is a warning naming the error, never a failed run)."""
        if self.report is None or not trainer.is_global_zero:
            return []
        paths = write_report(self.report, self.output_dir, extra=metrics)
        for logger in trainer.loggers:
            if type(logger).__name__ == "WandbLogger" and paths:
                logger.log_image(key="test/figure3", images=[str(p) for p in paths])
        return paths
