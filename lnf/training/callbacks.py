"""Evaluation callback: reduced rollouts, energy checks and Figure 3, apart from the LightningModule."""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any, Optional

import lightning.pytorch as pl
import numpy as np
import torch

from lnf.decoding_table import check_decoding
from lnf.boundary import is_clamped
from lnf.error_budget import read_error_budget
from lnf.evaluation import RolloutEvaluation, evaluate_rollouts, long_horizon_energy, reduction_subset
from lnf.integrators import Integrator, get_integrator
from lnf.quadrature import grid_shape_of, midpoint_grid
from lnf.tempfiles import write_text_atomic

log = logging.getLogger("lnf.evaluation")


def write_json_atomic(path: str | Path, payload: dict[str, Any]) -> Path:
    """Write JSON to a temporary name in the same folder, then rename (no half-written file)."""
    return write_text_atomic(path, json.dumps(payload, indent=2, sort_keys=True))


def save_evaluation_figures(result: RolloutEvaluation, scene: Any, grid_shape: Optional[tuple[int, ...]],
                            train_horizon: float, out_dir: Path, prefix: str, n_trajectories: int = 2,
                            integrator: "Integrator | dict | str | None" = None,
                            dt: Optional[float] = None) -> list[Path]:
    """Figure 3 (latent, energies, fields and errors before/after the horizon) for the first trajectories; fields
    on a midpoint grid of `grid_shape`, or on the scattered ``result.points`` when it is None.

    Each figure is written as ``<prefix>_trajectory<i>.png`` and, beside it, ``<prefix>_trajectory<i>.pdf``
    (:func:`lnf.plotting.save_figure`); the PNG paths are returned. The title names the trajectory, the
    integrator of the rollout (`integrator`: an object, name or {'name': ...} spec as :func:`get_integrator`
    takes it; left out of the title when None) and its time step (`dt` [s]; default the spacing of
    ``result.times``, the step :func:`evaluate_rollouts` integrates with)."""
    from lnf.plotting import _subscript, default_snapshot_indices, figure3, save_figure

    names = {"implicit_midpoint": "implicit midpoint", "rk4": "RK4", "dopri5": "Dormand–Prince 5(4)"}
    run, integ = [], None
    if integrator is not None:
        try:
            integ = get_integrator(integrator)
        except (TypeError, ValueError, KeyError):  # a spec it cannot build: named as given
            run.append(str(integrator))
        else:
            order = f" (order {integ.order})" if integ.name == "implicit_midpoint" else ""
            run.append(names.get(integ.name, integ.name) + order)
    times = np.asarray(result.times, dtype=float)
    if dt is None and len(times) > 1:
        dt = float(times[1] - times[0])
    if dt is not None:
        substeps = int(getattr(integ, "substeps", 1))
        if integ is not None and integ.name == "dopri5":
            run.append(f"adaptive steps, output every {dt:g} s")
        else:
            run.append(f"dt = {dt:g} s" + (f" in {substeps} substeps" if substeps > 1 else ""))
    paths = []
    idx = default_snapshot_indices(result.times, train_horizon)
    comp = scene.field_dim - 1  # vector fields: the last component (the vertical displacement of the elastic body)
    label = "field q" if scene.field_dim == 1 else f"field component q{_subscript(comp + 1)}"
    for i in range(min(n_trajectories, result.q_pred.shape[0])):
        energies = {k: v[i] for k, v in result.energies.items()}
        title = " · ".join([f"{prefix} trajectory {i}", *run])
        fig = figure3(result.times, result.q_pred[i], result.q_ref[i], energies, grid_shape, scene.bounds,
                      result.pred_fields[i, ..., comp], result.true_fields[i, ..., comp], idx, train_horizon,
                      title=title, field_label=label, points=result.points)
        paths.append(save_figure(fig, out_dir / f"{prefix}_trajectory{i}.png"))
    return paths


def stored_reference(split: Any, scene: Any, n: int, points: Optional[np.ndarray] = None) -> dict[str, Any]:
    """What a split stores beside its fields for its first `n` trajectories, as evaluate_rollouts takes it: the
    reference energies (stored, or from its states through the scene; absent when neither exists), the stored
    loads, and the quadrature weights of its points (of the indices `points` of them, if given)."""
    out: dict[str, Any] = {}
    parts = split.energy_parts(scene)
    if parts is not None:
        out["true_energies"] = tuple(np.asarray(e)[:n] for e in parts)
    if split.controls is not None:
        out["controls"] = split.controls[:n]
    if split.weights is not None:
        out["weights"] = split.weights if points is None else split.weights[points]
    return out


def _count(key: str, value: Any, minimum: int = 0) -> int:
    """An integer setting ≥ `minimum`, or a ValueError naming ``evaluation.<key>``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < minimum:
        raise ValueError(f"evaluation.{key} must be an integer ≥ {minimum}, got {value!r}")
    return int(value)


def _positive(key: str, value: Any) -> float:
    """A finite number > 0, or a ValueError naming ``evaluation.<key>``."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not np.isfinite(value) or value <= 0:
        raise ValueError(f"evaluation.{key} must be a finite number > 0, got {value!r}")
    return float(value)


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
    """

    def __init__(self, integrator: "Integrator | dict | str" = "implicit_midpoint", output_dir: str = ".",
                 every_n_epochs: int = 5, val_trajectories: int = 4, val_resolution: int = 32,
                 long_steps: int = 10000, long_trajectories: int = 4, long_dt: float = 0.05,
                 figures: int = 2, max_reduction_points: Optional[int] = 1024, decoding: str = "auto") -> None:
        super().__init__()
        try:
            self.integrator = get_integrator(integrator)
        except (TypeError, ValueError, KeyError) as err:
            raise ValueError(f"integrator={integrator!r}: {err}") from err
        self.output_dir = Path(output_dir)
        self.every_n_epochs = _count("every_n_epochs", every_n_epochs)
        self.val_trajectories = _count("val_trajectories", val_trajectories, minimum=1)
        self.val_resolution = _count("val_resolution", val_resolution, minimum=1)
        self.long_steps = _count("long_steps", long_steps)
        self.long_trajectories = _count("long_trajectories", long_trajectories, minimum=1)
        self.long_dt = _positive("long_dt", long_dt)
        self.figures = _count("figures", figures)
        check_decoding(decoding, "evaluation.decoding")
        self.decoding = decoding
        self.max_reduction_points = None if max_reduction_points is None else \
            _count("max_reduction_points", max_reduction_points, minimum=1)
        self.test_metrics: dict[str, float] = {}
        self._val_count = 0
        self._figure_inputs: Optional[tuple[RolloutEvaluation, Any, tuple[int, ...], float]] = None

    def state_dict(self) -> dict[str, Any]:  # saved in checkpoints: a resumed run rolls out at the same epochs
        return {"val_count": self._val_count}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._val_count = int(state_dict.get("val_count", 0))

    @staticmethod
    def _train_horizon(split: Any) -> float:
        return float(split.times[split.train_times]) if split.train_times < len(split.times) else float(split.times[-1])

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
        stored = split.from_arrays or split.states.shape[-1] == 0 or not scene.provides("fields")
        if stored:  # the stored fields on (a strided subset of at most val_resolution^dim_B of) the stored points
            sub = reduction_subset(len(split.fine_points), None, self.val_resolution ** scene.body_dim)
            points, truth = split.fine_points[sub], {"true_fields": split.fields[:n][:, :, sub],
                                                     "true_velocities": split.velocities[:n][:, :, sub]}
        else:
            points, truth = midpoint_grid(self.val_resolution, scene.bounds).numpy(), {}
        with torch.inference_mode(False), torch.no_grad():
            result = evaluate_rollouts(pl_module.model, split.states[:n], split.times, points,
                                       self._train_horizon(split), integrator=self.integrator,
                                       label=f"validation rollout (epoch {trainer.current_epoch})",
                                       decoding=self.decoding,
                                       **truth, **stored_reference(split, scene, n, sub if stored else None))
        keys = ["field_rel_l2/all/median", "field_rel_l2/extrapolation/median", "projection_rel_l2/all/median",
                "energy_rel_err/max", "latent_rmse/median", "vpt/median"]
        for key in keys:
            pl_module.log(f"val/{key}", result.metrics[key], sync_dist=True)

    def on_test_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        model = pl_module.model
        split = trainer.datamodule.split("test")
        horizon = self._train_horizon(split)
        start = time.perf_counter()
        grid_shape = grid_shape_of(split.fine_points, model.scene.bounds)  # None: scattered points
        with torch.inference_mode(False), torch.no_grad():
            result = evaluate_rollouts(model, split.states, split.times, split.fine_points, horizon,
                                       true_fields=split.fields, true_velocities=split.velocities,
                                       integrator=self.integrator, grid_shape=grid_shape,
                                       max_reduction_points=self.max_reduction_points, label="test rollout",
                                       decoding=self.decoding,
                                       **stored_reference(split, model.scene, len(split)))
            metrics = dict(result.metrics)
            if self.long_steps > 0:
                n = min(self.long_trajectories, len(split))
                metrics.update(long_horizon_energy(
                    model, split.states[:n, 0], split.fine_points, self.long_dt, self.long_steps,
                    integrator=self.integrator, grid_shape=grid_shape, max_reduction_points=self.max_reduction_points,
                    initial_fields=(split.fields[:n, 0], split.velocities[:n, 0]),
                    controls=None if split.controls is None else split.controls[:n]))
        metrics["evaluation_seconds"] = time.perf_counter() - start
        self.test_metrics = metrics
        for finding in read_error_budget(metrics, clamped=is_clamped(model)):
            log.warning("test rollout: %s", finding)
        for key, value in metrics.items():  # equal on every rank (each evaluates the whole split)
            pl_module.log(f"test/{key}", float(value), sync_dist=True)
        # Figure 3 is drawn by draw_figures() once metrics.json and last.ckpt are written: a figure that
        # cannot be drawn must not cost the results
        self._figure_inputs = (result, model.scene, grid_shape, horizon)

    def draw_figures(self, trainer: pl.Trainer) -> list[Path]:
        """Figure 3 of the last test evaluation (PNG and wandb), on rank 0; a figure that cannot be drawn is a
        warning naming the error, never a failed run."""
        if self._figure_inputs is None or not trainer.is_global_zero or self.figures == 0:
            return []
        result, scene, grid_shape, horizon = self._figure_inputs
        self._figure_inputs = None
        try:
            paths = save_evaluation_figures(result, scene, grid_shape, horizon, self.output_dir / "figures",
                                            "test", self.figures, integrator=self.integrator)
            self._log_images(trainer, paths)
        except Exception as err:  # noqa: BLE001 - any drawing failure is reported, the results are kept
            log.warning("could not draw Figure 3 (%s: %s); metrics.json and the checkpoints are written",
                        type(err).__name__, err)
            return []
        return paths

    @staticmethod
    def _log_images(trainer: pl.Trainer, paths: list[Path]) -> None:
        for logger in trainer.loggers:
            if type(logger).__name__ == "WandbLogger" and paths:
                logger.log_image(key="test/figure3", images=[str(p) for p in paths])
