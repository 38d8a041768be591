"""The one path from a trained model to its metrics: an evaluation spec, the data, :func:`evaluate_model` → a report.

``lnf.train`` (its test and validation rollouts, :mod:`lnf.training.callbacks`), ``lnf.evaluate`` and the studies
(``experiments/scenes.py``) evaluate through :func:`evaluate_model`; :func:`write_report` is the only writer of
``metrics.json`` and of the evaluation figures (Figure 3). No Lightning or Hydra here.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch

from lnf.boundary import is_clamped
from lnf.dataset import (SOURCE_ARRAYS, DatasetConfig, evaluation_data, load_split, stored_generation,
                         verify_dataset, warn_if_changed)
from lnf.decoding_table import check_decoding
from lnf.error_budget import read_error_budget
from lnf.evaluation import RolloutEvaluation, evaluate_rollouts, long_horizon_energy
from lnf.integrators import get_integrator
from lnf.metrics import time_windows
from lnf.quadrature import grid_shape_of
from lnf.reduced_model import ReducedModel
from lnf.tempfiles import write_json_atomic
from lnf.utils import EVALUATION_RULES, require

log = logging.getLogger("lnf.evaluation")


@dataclass(frozen=True)
class EvaluationSpec:
    """How to evaluate: the settings that ``evaluation:`` of train.yaml and evaluate.yaml share (checked here,
    each refusal naming ``evaluation.<key>``).

    `integrator` and `quadrature` (None: the model's rule) roll out; `split` names the figures
    (``<split>_trajectory<i>.png``) and, unless `label` says otherwise, the rollout in messages (``<split>
    rollout``); `long_steps` > 0 adds the long-horizon energy check on the first `long_trajectories` trajectories
    at `long_dt` [s] (None: the data's spacing); `figures` trajectories get a Figure 3; `keep_fields` trajectories
    keep their fields in the result (None: all); `progress` shows progress bars (not inside a Lightning run);
    `closure_shooting_iterations` bounds the shooting search of a closure fitted with this spec
    (:func:`lnf.closure_choice.shoot_closure`: Levenberg–Marquardt iterations per closure term in each stage; 0: the
    residual fit alone)."""

    integrator: Any = "implicit_midpoint"
    quadrature: Any = None
    split: str = "test"
    label: Optional[str] = None
    max_reduction_points: Optional[int] = 1024
    decoding: str = "auto"
    long_steps: int = 0
    long_trajectories: int = 4
    long_dt: Optional[float] = None
    figures: int = 0
    keep_fields: Optional[int] = None
    progress: bool = False
    closure_shooting_iterations: int = 20

    def __post_init__(self) -> None:
        for key, rule in EVALUATION_RULES.items():
            require(f"evaluation.{key}", getattr(self, key), rule)
        require("evaluation.long_dt", self.long_dt, (">", 0, None, "", "", "the data's spacing"))
        check_decoding(self.decoding, "evaluation.decoding")

    @property
    def rollout_label(self) -> str:
        return self.label or f"{self.split} rollout"


@dataclass
class EvaluationData:
    """The trajectories to evaluate: full-order `states` (n, T, S) at `times` (T,) [s] on the evaluation `points`
    (N, dim_B) (a row-major grid of `grid_shape`, or scattered: None), with extrapolation from `train_horizon` [s].
    What is not given comes from the scene (see :func:`lnf.evaluation.evaluate_rollouts`): the true fields and
    velocities (n, T, N, A), the reference energies (kinetic, potential) (n, T), the loads (n, c), the points'
    quadrature weights (N,); `start_fields` (fields, velocities) (n, N, A) start the long-horizon check (default:
    the true fields at t0)."""

    states: np.ndarray
    times: np.ndarray
    points: np.ndarray
    train_horizon: float
    grid_shape: Optional[tuple[int, ...]] = None
    true_fields: Optional[np.ndarray] = None
    true_velocities: Optional[np.ndarray] = None
    true_energies: Optional[tuple[np.ndarray, np.ndarray]] = None
    controls: Optional[np.ndarray] = None
    weights: Optional[np.ndarray] = None
    start_fields: Optional[tuple[np.ndarray, np.ndarray]] = None

    @classmethod
    def of_split(cls, split: Any, scene: Any, n: Optional[int] = None, stride: int = 1,
                 grid_shape: Optional[tuple[int, ...]] = None, subset: Optional[np.ndarray] = None) -> "EvaluationData":
        """The first `n` stored trajectories of `split` (all by default), every `stride`-th sample, on its fine points
        (or the indices `subset` of them), with what the split stores beside its fields. `grid_shape` None: the
        fine points' own grid where they are one (:func:`lnf.quadrature.grid_shape_of`), so that ρ̃ of the true
        initial fields reads the same evenly strided sub-grid whoever evaluates (a flat stride through a 64² grid
        keeps every 4th column: the double pendulum's test error was 0.0805 through it, 0.0623 through the 32²
        sub-grid)."""
        n = len(split) if n is None else min(int(n), len(split))
        if grid_shape is None and subset is None:
            grid_shape = grid_shape_of(split.fine_points, scene.bounds)

        def frames(a: np.ndarray) -> np.ndarray:
            a = a[:n, ::stride]
            return a if subset is None else a[:, :, subset]

        parts = split.energy_parts(scene)
        times = split.times
        return cls(states=split.states[:n, ::stride], times=times[::stride],
                   points=split.fine_points if subset is None else split.fine_points[subset],
                   train_horizon=float(times[min(split.train_times, len(times) - 1)]), grid_shape=grid_shape,
                   true_fields=frames(split.fields), true_velocities=frames(split.velocities),
                   true_energies=None if parts is None else tuple(np.asarray(e)[:n, ::stride] for e in parts),
                   controls=None if split.controls is None else split.controls[:n],
                   weights=None if split.weights is None else
                   (split.weights if subset is None else split.weights[subset]))

    def within_horizon(self) -> "EvaluationData":
        """The same trajectories cut to the samples before `train_horizon`: the in-horizon window's metrics are the
        same and the rollouts half as long where the data run twice the horizon (a choice read off in-horizon errors,
        as the closure's, rolls out no further)."""
        keep = int(np.count_nonzero(time_windows(np.asarray(self.times), self.train_horizon)["in_horizon"]))
        if keep < 2 or keep == len(self.times):
            return self

        def cut(a: Optional[np.ndarray]) -> Optional[np.ndarray]:
            return None if a is None else a[:, :keep]

        return replace(self, states=cut(self.states), times=self.times[:keep], true_fields=cut(self.true_fields),
                       true_velocities=cut(self.true_velocities),
                       true_energies=None if self.true_energies is None else tuple(cut(e) for e in self.true_energies))


@dataclass
class EvaluationReport:
    """What :func:`evaluate_model` found: the metrics, the rollouts behind them, and what was evaluated how."""

    metrics: dict[str, float]
    rollouts: RolloutEvaluation
    data: EvaluationData
    spec: EvaluationSpec
    scene: Any
    clamped: bool
    closed: bool = False  # the model's dynamics carry a fitted potential closure (lnf/closure.py)
    collapse_advice: Optional[str] = None  # what the model says to try when its embedding collapsed


@torch.no_grad()
def evaluate_model(model: ReducedModel, data: EvaluationData, spec: EvaluationSpec) -> EvaluationReport:
    """Roll `model` out on `data` as `spec` says: the docs/method.md §7.3 metrics
    (:func:`lnf.evaluation.evaluate_rollouts`), the long-horizon energy check where ``spec.long_steps`` > 0
    (:func:`lnf.evaluation.long_horizon_energy`) and ``evaluation_seconds``. Writes nothing (:func:`write_report`)."""
    start = time.perf_counter()
    result = evaluate_rollouts(model, data.states, data.times, data.points, data.train_horizon,
                               true_fields=data.true_fields, true_velocities=data.true_velocities,
                               integrator=spec.integrator, quadrature=spec.quadrature, grid_shape=data.grid_shape,
                               max_reduction_points=spec.max_reduction_points, label=spec.rollout_label,
                               true_energies=data.true_energies, controls=data.controls, weights=data.weights,
                               keep_fields=spec.keep_fields, progress=spec.progress, decoding=spec.decoding)
    metrics = {**result.metrics, **long_horizon_check(model, data, spec)}
    metrics["evaluation_seconds"] = time.perf_counter() - start
    return EvaluationReport(metrics, result, data, spec, model.scene, is_clamped(model), closed=model.has_closure,
                            collapse_advice=model.collapse_advice)


def long_horizon_check(model: ReducedModel, data: EvaluationData, spec: EvaluationSpec) -> dict[str, float]:
    """The long-horizon energy check of `spec` (``energy_drift_long/*``; {} when ``spec.long_steps`` is 0): the first
    ``spec.long_trajectories`` trajectories of `data` rolled out ``spec.long_steps`` steps of ``spec.long_dt`` (None:
    the data's spacing) from their start fields (the true fields at t0 where `data` holds them, else the scene's)."""
    if spec.long_steps <= 0:
        return {}
    k = min(spec.long_trajectories, len(data.states))
    fields = data.start_fields if data.start_fields is not None or data.true_fields is None else \
        (data.true_fields[:, 0], data.true_velocities[:, 0])
    return long_horizon_energy(
        model, data.states[:k, 0], data.points, spec.long_dt or float(data.times[1] - data.times[0]), spec.long_steps,
        integrator=spec.integrator, quadrature=spec.quadrature, grid_shape=data.grid_shape,
        max_reduction_points=spec.max_reduction_points,
        initial_fields=None if fields is None else tuple(np.asarray(f[:k]) for f in fields),
        controls=None if data.controls is None else data.controls[:k], progress=spec.progress)


def split_long_check(model: ReducedModel, split: Any, n: int, steps: int, integrator: Any,
                     dt: Optional[float] = None) -> dict[str, float]:
    """:func:`long_horizon_check` of the first `n` trajectories of a loaded `split` over `steps` steps of `dt` [s]
    (None: the split's spacing), started from the scene's fields of their initial states."""
    data = EvaluationData(split.states[:n], split.times, split.fine_points, float(split.times[-1]))
    spec = EvaluationSpec(integrator=integrator, long_steps=steps, long_trajectories=n, long_dt=dt)
    return long_horizon_check(model, data, spec)


def write_report(report: EvaluationReport, output_dir: Path, extra: Optional[dict[str, float]] = None,
                 logger: logging.Logger = log) -> list[Path]:
    """Log what the metrics say about the error budget, write ``metrics.json`` (the report's metrics and `extra`)
    into `output_dir`, then Figure 3 of the first ``spec.figures`` trajectories into ``output_dir/figures``;
    returns the figures' PNG paths. A figure that cannot be drawn is a warning: the metrics are written first."""
    for finding in read_error_budget(report.metrics, clamped=report.clamped, closed=report.closed,
                                     collapse_advice=report.collapse_advice):
        logger.warning("%s: %s", report.spec.rollout_label, finding)
    write_json_atomic(Path(output_dir) / "metrics.json", {**report.metrics, **(extra or {})})
    if report.spec.figures <= 0:
        return []
    try:  # a figure that fails (a plotting backend, a full disk) must not cost the results
        return save_evaluation_figures(report.rollouts, report.scene, report.data.grid_shape,
                                       report.data.train_horizon, Path(output_dir) / "figures", report.spec.split,
                                       report.spec.figures, integrator=report.spec.integrator)
    except Exception as err:  # noqa: BLE001
        logger.warning("could not draw Figure 3: %s: %s (metrics.json is written in %s)", type(err).__name__, err,
                       output_dir)
        return []


def save_evaluation_figures(result: RolloutEvaluation, scene: Any, grid_shape: Optional[tuple[int, ...]],
                            train_horizon: float, out_dir: Path, prefix: str, n_trajectories: int = 2,
                            integrator: Any = None, dt: Optional[float] = None) -> list[Path]:
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


def checkpoint_data(model: Any, data_dir: Path) -> tuple[Path, Optional[DatasetConfig]]:
    """The dataset that a loaded checkpoint was trained on, ready to evaluate, and its generation settings (None for
    trajectories written from a user's arrays, which are verified, never regenerated; a warning names what was
    rewritten since). A generated one outside `data_dir` is only read (:func:`lnf.dataset.evaluation_data`); a
    file whose content changed since training is named in a warning."""
    data = dict(model.checkpoint.get("data") or {})
    if not data:
        raise ValueError(f"checkpoint {model.checkpoint.get('path')} records no data settings; cannot find its "
                         f"test trajectories")
    path = Path(data.pop("path"))
    on_mismatch = data.pop("on_mismatch", "regenerate")
    explicit = bool(data.pop("explicit_path", False))  # a shared file of another run's settings is not overwritten
    trained_checksum = data.pop("checksum", None) or model.checkpoint.get("data_checksum")
    dcfg = None
    if data.get("source") == SOURCE_ARRAYS:  # a user's trajectories: verified, never regenerated
        verify_dataset(path, model.scene)
        now, then = stored_generation(path), data.get("generation") or {}
        changed = sorted(k for k in set(now) | set(then) if now.get(k) != then.get(k))
        if changed:
            log.warning("%s was rewritten since the checkpoint was trained on it (%s); evaluating the file as it is now",
                        path, "; ".join(f"{k}: trained on {then.get(k)!r}, now {now.get(k)!r}" for k in changed))
    else:
        dcfg = DatasetConfig.from_mapping(data)
        path = evaluation_data(model.scene, dcfg, path, Path(data_dir), on_mismatch, explicit)
    warn_if_changed(path, trained_checksum)
    return path, dcfg


@torch.no_grad()
def ensure_code_range(model: Any, path: Path, dcfg: Optional[DatasetConfig]) -> None:
    """A tabulated dynamics needs the training codes' range; a checkpoint written before lnf recorded it gets
    it here from the training split (its training samples, reduced on the coarse grid)."""
    if getattr(model, "tabulation", None) is None or bool(torch.isfinite(model.code_low).all()):
        return
    train = load_split(path, "train", scene=model.scene, cfg=dcfg)
    p = model.reference_tensor()
    points = torch.as_tensor(train.coarse_points, dtype=p.dtype)
    fields = torch.as_tensor(train.coarse_fields[:, : train.train_times], dtype=p.dtype).flatten(0, 1)
    codes = torch.cat([model.reduce(points, fields[i:i + 256]) for i in range(0, len(fields), 256)])
    model.track_code_range(codes, reset=True)
    log.info("the checkpoint has no range of training codes: took it from %d training snapshots: %s .. %s",
             len(fields), model.code_low.tolist(), model.code_high.tolist())

