"""Reduced rollouts on held-out trajectories and their metrics (shared by the callback and `lnf.evaluate`).

Protocol (DESIGN.md §3, §6): q̃0 = ρ̃(q(t0)) and q̃̇0 = (dφ)^{†,ω0} q̇(t0) from the fields on the evaluation
points; roll the reduced dynamics out over all samples; decode on the evaluation points; compare with
the true fields, with the projected reference q̃_ref(t) = ρ̃(q(t)) and with the true energies.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from lnf import metrics as M
from lnf.integrators import Integrator, get_integrator
from lnf.reduced_model import ReducedModel
from lnf.quadrature import Quadrature, QuadratureRule

log = logging.getLogger("lnf.evaluation")


@dataclass
class RolloutEvaluation:
    """Metrics plus the arrays behind them (n trajectories, T samples, N evaluation points)."""

    metrics: dict[str, float]
    times: np.ndarray  # (T,)
    q_pred: np.ndarray  # (n, T, d)
    q_ref: np.ndarray  # (n, T, d)
    pred_fields: np.ndarray  # (n, T, N, A)
    true_fields: np.ndarray  # (n, T, N, A)
    energies: dict[str, np.ndarray] = field(default_factory=dict)  # each (n, T)
    points: Optional[np.ndarray] = None  # (N, dim_B)


def reduction_subset(n_points: int, grid_shape: Optional[tuple[int, ...]], max_points: Optional[int]) -> np.ndarray:
    """Indices of the evaluation points that ρ̃ uses: all, or an evenly strided subset of ≤ max_points.

    On a row-major grid the stride is the same along every axis (64×64 → every 2nd point → 32×32);
    on scattered points it is every k-th point.
    """
    if not max_points or n_points <= max_points:
        return np.arange(n_points)
    if grid_shape is not None and int(np.prod(grid_shape)) == n_points:
        stride = int(np.ceil((n_points / max_points) ** (1.0 / len(grid_shape))))
        idx = np.arange(n_points).reshape(grid_shape)[tuple(slice(None, None, stride) for _ in grid_shape)]
        return idx.reshape(-1)
    return np.arange(0, n_points, int(np.ceil(n_points / max_points)))


def trajectory_controls(scene, states0: np.ndarray, like: Tensor) -> Optional[Tensor]:
    """The scene's per-trajectory load parameters (n, c) from initial full-order states (n, S), or None."""
    controls = scene.controls(np.asarray(states0))
    return None if controls is None else torch.as_tensor(controls, dtype=like.dtype, device=like.device)


def reference_fields(scene, states: np.ndarray, points: np.ndarray, label: str) -> tuple[np.ndarray, np.ndarray]:
    """The true fields (…, N, A) of full-order states (…, S) at `points` from ``scene.fields``; where the scene has
    no fields() or the states are empty (trajectories written from arrays), an error saying to evaluate on the
    stored points and times."""
    if np.shape(states)[-1] == 0 or not scene.provides("fields"):
        why = "the trajectories hold no full-order states" if np.shape(states)[-1] == 0 else \
            f"scene {scene.name!r} defines no fields()"
        raise ValueError(f"{label}: the true fields at other points or times need the scene's fields() of "
                         f"full-order states, and {why}: evaluate trajectories written from arrays on their stored "
                         f"points and times (lnf.evaluate grid.kind=stored, without dt=, horizon= or "
                         f"initial_states=)")
    return scene.fields(states, points)


def divergence_steps(diverged_step: "Tensor | np.ndarray", non_finite: Optional[np.ndarray] = None,
                     record_every: int = 1) -> np.ndarray:
    """Per trajectory (n,), the integration step at which it diverged, −1 where it did not.

    A trajectory diverged where the integrator says so (`diverged_step` ≥ 0: its state became non-finite or
    exceeded the bound) or where a recorded quantity such as its energy is non-finite: `non_finite` (n, R)
    marks the recorded samples (every `record_every` steps); the earlier of the two counts.
    """
    steps = np.asarray(diverged_step.cpu() if isinstance(diverged_step, Tensor) else diverged_step,
                       dtype=np.int64).reshape(-1).copy()
    if non_finite is not None:
        bad = np.asarray(non_finite, dtype=bool).reshape(len(steps), -1)
        first = np.where(bad.any(-1), bad.argmax(-1) * int(record_every), -1)
        steps = np.where((first >= 0) & ((steps < 0) | (first < steps)), first, steps)
    return steps


def divergence_metrics(steps: np.ndarray, dt: float, t0: float = 0.0, suffix: str = "",
                       label: str = "rollout") -> dict[str, float]:
    """`diverged_count`, `diverged_fraction`, `first_divergence_step` and `first_divergence_time` [s] (+ `suffix`)
    from per-trajectory divergence steps (n,) (−1: stayed finite; see :func:`divergence_steps`).

    The first step and time are the earliest over the trajectories; both are −1.0 when none diverged (JSON has
    no NaN). A divergence is also logged as a warning (logger ``lnf.evaluation``) naming the `label`ed rollout.
    """
    steps = np.asarray(steps).reshape(-1)
    hit = steps >= 0
    count = int(hit.sum())
    first = int(steps[hit].min()) if count else -1
    when = float(t0 + first * dt) if count else -1.0
    if count:
        which = np.flatnonzero(hit).tolist()
        log.warning("%s: %d of %d trajectories diverged (non-finite or exploding state or energy), the first at "
                    "step %d (t = %.6g s, dt = %g s); trajectories %s%s. Try a smaller dt, integrator.substeps or "
                    "another integrator.", label, count, len(steps), first, when, dt, which[:10],
                    " …" if len(which) > 10 else "")
    return {f"diverged_count{suffix}": float(count), f"diverged_fraction{suffix}": count / max(len(steps), 1),
            f"first_divergence_step{suffix}": float(first), f"first_divergence_time{suffix}": when}


def _chunked(fn, x: Tensor, chunk: int) -> Tensor:
    return torch.cat([fn(x[i:i + chunk]) for i in range(0, x.shape[0], chunk)], dim=0)


@torch.no_grad()
def evaluate_rollouts(
    model: ReducedModel,
    states: np.ndarray,
    times: np.ndarray,
    points: np.ndarray,
    train_horizon: float,
    true_fields: Optional[np.ndarray] = None,
    true_velocities: Optional[np.ndarray] = None,
    integrator: "str | Integrator | dict" = "implicit_midpoint",
    quadrature: "Quadrature | QuadratureRule | None" = None,
    snapshot_chunk: int = 32,
    grid_shape: Optional[tuple[int, ...]] = None,
    max_reduction_points: Optional[int] = 1024,
    label: str = "rollout",
    true_energies: Optional[tuple[np.ndarray, np.ndarray]] = None,
    controls: Optional[np.ndarray] = None,
    weights: Optional[np.ndarray] = None,
) -> RolloutEvaluation:
    """Roll out every trajectory of full-order `states` (n, T, S) sampled at `times` (T,) [s].

    `points` (N, dim_B) are the evaluation points (equal quadrature weights |B|/N); the true fields there
    come from `true_fields`/`true_velocities` (n, T, N, A) when given, else from the scene. Decoding and
    errors use all N points; ρ̃ (initial conditions and the projected reference q̃_ref) uses an evenly
    strided subset of at most `max_reduction_points` of them (see :func:`reduction_subset`).

    Trajectories written from arrays give what a scene would compute from its states: `true_energies` (kinetic,
    potential) (n, T) each (else ``scene.true_energy_parts(states)``; with neither, the energy errors are left
    out), `controls` (n, c) (else ``scene.controls``) and the points' quadrature `weights` (N,) that weight the
    field errors (default: equal weights).

    Divergence: `diverged_fraction`, `diverged_count`, `first_divergence_step` and `first_divergence_time` [s]
    (the earliest over the trajectories, −1.0 when none diverged; see :func:`divergence_metrics`); a trajectory
    diverged where its state or its energy became non-finite. It is also logged as a warning naming `label`.
    """
    if points.ndim != 2 or points.shape[0] == 0:
        raise ValueError(f"evaluation grid has no points: expected shape (N ≥ 1, dim_B), got {points.shape}")
    scene = model.scene
    p = model.reference_tensor()
    if true_fields is None or true_velocities is None:
        true_fields, true_velocities = reference_fields(scene, states, points, label)
    n, T = states.shape[:2]
    dt = float(times[1] - times[0])
    pts = torch.as_tensor(points, dtype=p.dtype, device=p.device)
    if model.state_is_field:
        max_reduction_points = None  # the full-order model takes the whole field as its state
    sub = reduction_subset(len(points), grid_shape, max_reduction_points)
    pts_r = pts[torch.as_tensor(sub, device=p.device)]
    fields_r = torch.as_tensor(np.asarray(true_fields)[:, :, sub], dtype=p.dtype, device=p.device)
    vel0 = torch.as_tensor(np.asarray(true_velocities)[:, 0, sub], dtype=p.dtype, device=p.device)

    q0 = model.reduce(pts_r, fields_r[:, 0])
    v0 = model.project_velocity(q0, pts_r, vel0)
    integ = get_integrator(integrator)
    dynamics = model.dynamics(quadrature)  # a tabulated dynamics is built (and cached) here, outside the timing
    table_info = dict(getattr(dynamics, "info", {}))
    counts0 = (getattr(dynamics, "fallback_rows", 0), getattr(dynamics, "evaluated_rows", 0))
    start = time.perf_counter()
    controls = trajectory_controls(scene, states[:, 0], q0) if controls is None else \
        torch.as_tensor(np.asarray(controls), dtype=q0.dtype, device=q0.device)
    traj = model.rollout(q0, v0, dt=dt, steps=T - 1, integrator=integ, on_divergence="mark", controls=controls,
                         dynamics=dynamics)
    rollout_seconds = time.perf_counter() - start
    if "table_nodes" in table_info:  # share of the rollout's evaluations that left the table's box (exact there)
        table_info["table_fallback_fraction"] = (dynamics.fallback_rows - counts0[0]) / max(
            dynamics.evaluated_rows - counts0[1], 1)

    d = model.latent_dim
    flat_q = traj.q.reshape(n * T, d)
    finite = torch.isfinite(flat_q).all(-1)
    safe_q = torch.where(finite[:, None], flat_q, torch.zeros_like(flat_q))
    start = time.perf_counter()
    pred = _chunked(lambda c: model.decode(c, pts), safe_q, snapshot_chunk)
    decode_seconds = time.perf_counter() - start
    pred = torch.where(finite[:, None, None], pred, float("nan")).reshape(n, T, *pred.shape[1:])
    flat_fields = fields_r.reshape(n * T, *fields_r.shape[2:])
    q_ref = _chunked(lambda f: model.reduce(pts_r, f), flat_fields, snapshot_chunk)
    proj = _chunked(lambda c: model.decode(c, pts), q_ref, snapshot_chunk).reshape(n, T, *pred.shape[2:])

    kin, pot = model.energy(torch.where(finite[:, None], flat_q, 0.0),
                            torch.where(finite[:, None], traj.v.reshape(n * T, d), 0.0), quadrature)
    kin = torch.where(finite, kin, float("nan")).reshape(n, T).double().cpu().numpy()
    pot = torch.where(finite, pot, float("nan")).reshape(n, T).double().cpu().numpy()
    if true_energies is None and states.shape[-1] > 0 and scene.provides("true_energy_parts"):
        true_energies = scene.true_energy_parts(states)
    if true_energies is None:
        log.info("%s: no reference energies (the trajectories were written without energies or states): the energy "
                 "errors are left out", label)
        kin_true = pot_true = np.full((n, T), np.nan)
    else:
        kin_true, pot_true = (np.asarray(e, dtype=np.float64) for e in true_energies)

    if weights is None:
        weights = np.full(points.shape[0], 1.0 / points.shape[0])
    else:
        weights = np.asarray(weights, dtype=np.float64) / float(np.sum(weights))
    pred_np = pred.double().cpu().numpy()
    true_np = np.asarray(true_fields, dtype=np.float64)
    metrics: dict[str, float] = {}
    metrics.update(M.field_metrics("field_rel_l2", pred_np, true_np, weights, times, train_horizon))
    metrics.update(M.field_metrics("projection_rel_l2", proj.double().cpu().numpy(), true_np, weights, times,
                                   train_horizon))
    q_pred_np = traj.q.double().cpu().numpy()
    q_ref_np = q_ref.reshape(n, T, d).double().cpu().numpy()
    metrics.update(M.latent_rmse(q_pred_np, q_ref_np))
    if true_energies is not None:
        metrics.update(M.energy_metrics(kin + pot, kin_true + pot_true, scene.energy_scale))
    vpt = M.valid_prediction_time(pred_np, true_np, weights, times)
    metrics.update({f"vpt/{k}": v for k, v in M.summarize(vpt).items()})
    metrics["vpt/median"] = float(np.median(vpt))
    metrics["vpt/min"] = float(np.min(vpt))
    metrics.pop("vpt/max", None)
    metrics.update(divergence_metrics(divergence_steps(traj.diverged_step, ~np.isfinite(kin + pot)), dt,
                                      float(times[0]), label=label))
    metrics["rollout_seconds_per_trajectory"] = rollout_seconds / n
    metrics["rollout_seconds_per_step"] = rollout_seconds / max(T - 1, 1)
    metrics["decode_seconds_per_trajectory"] = decode_seconds / n  # all T frames on the N evaluation points
    metrics["frames"] = float(T)
    metrics["evaluation_points"] = float(len(points))
    metrics["fields_seconds_per_trajectory"] = (rollout_seconds + decode_seconds) / n  # rollout + decoding
    for key in ("table_nodes", "table_points", "table_error", "table_seconds", "table_fallback_fraction"):  # offline cost of a tabulated dynamics
        if key in table_info:
            metrics[key] = float(table_info[key])
    return RolloutEvaluation(
        metrics=metrics, times=np.asarray(times), q_pred=q_pred_np, q_ref=q_ref_np, pred_fields=pred_np,
        true_fields=true_np, points=np.asarray(points),
        energies={"kinetic_pred": kin, "potential_pred": pot, "kinetic_true": kin_true, "potential_true": pot_true},
    )


@torch.no_grad()
def long_horizon_energy(
    model: ReducedModel,
    states0: np.ndarray,
    points: np.ndarray,
    dt: float,
    steps: int,
    integrator: "str | Integrator | dict" = "implicit_midpoint",
    quadrature: "Quadrature | QuadratureRule | None" = None,
    record_every: int = 10,
    grid_shape: Optional[tuple[int, ...]] = None,
    max_reduction_points: Optional[int] = 1024,
    initial_fields: Optional[tuple[np.ndarray, np.ndarray]] = None,
    controls: Optional[np.ndarray] = None,
) -> dict[str, float]:
    """energy_drift = max_t |Ẽ(t) − Ẽ(0)| / E_scale over a `steps`-step rollout from full-order states (n, S).

    Returns `energy_drift_long/{median,max,steps,seconds}` and where the rollout diverged:
    `diverged_count_long`, `diverged_fraction_long`, `first_divergence_step_long` and
    `first_divergence_time_long` [s] (−1.0 when none diverged; a non-finite state or energy counts), also logged
    as a warning (see :func:`divergence_metrics`).
    """
    scene = model.scene
    p = model.reference_tensor()
    if model.state_is_field:
        max_reduction_points = None
    sub = reduction_subset(len(points), grid_shape, max_reduction_points)
    points = np.asarray(points)[sub]
    if initial_fields is None:
        q_true, v_true = (a[:, 0] for a in reference_fields(scene, states0[:, None], points, "long-horizon check"))
    else:  # the stored fields at t0 (n, N, A) on all points
        q_true, v_true = (np.asarray(a)[:, sub] for a in initial_fields)
    pts = torch.as_tensor(points, dtype=p.dtype, device=p.device)
    q0 = model.reduce(pts, torch.as_tensor(q_true, dtype=p.dtype, device=p.device))
    v0 = model.project_velocity(q0, pts, torch.as_tensor(v_true, dtype=p.dtype, device=p.device))
    start = time.perf_counter()
    traj = model.rollout(q0, v0, dt=dt, steps=steps, integrator=integrator, quadrature=quadrature,
                         record_every=record_every, on_divergence="mark",
                         controls=trajectory_controls(scene, states0, q0) if controls is None else
                         torch.as_tensor(np.asarray(controls), dtype=q0.dtype, device=q0.device))
    seconds = time.perf_counter() - start
    kin, pot = model.energy(torch.nan_to_num(traj.q), torch.nan_to_num(traj.v), quadrature)
    energy = (kin + pot).double().cpu().numpy()
    diverged = divergence_steps(traj.diverged_step, ~np.isfinite(energy), record_every)
    energy[diverged >= 0] = np.nan
    drift = np.max(np.abs(energy - energy[:, :1]), axis=-1) / scene.energy_scale
    out = {f"energy_drift_long/{k}": v for k, v in M.summarize(drift).items()}
    out["energy_drift_long/steps"] = float(steps)
    out["energy_drift_long/seconds"] = seconds
    out.update(divergence_metrics(diverged, dt, suffix="_long", label="long-horizon energy check"))
    return out
