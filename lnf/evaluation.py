"""Reduced rollouts on held-out trajectories and their metrics (shared by the callback and `lnf.evaluate`).

Protocol (docs/method.md §7.2): q̃0 = ρ̃(q(t0)) and q̃̇0 = (dφ)† q̇(t0) († the ω0-weighted pseudo-inverse)
from the fields on the evaluation points; roll the reduced dynamics out over all samples; decode on the evaluation
points; compare with the true fields, with the projected reference q̃_ref(t) = ρ̃(q(t)) and with the true energies.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import torch
from torch import Tensor

from lnf import metrics as M
from lnf.decoding_table import DecodingTable, TabulatedField, check_decoding, code_box
from lnf.integrators import Integrator, get_integrator
from lnf.progress import progress_bar
from lnf.reduced_model import ReducedModel
from lnf.quadrature import Quadrature, QuadratureRule
from lnf.divergence import divergence_metrics, divergence_steps, initial_state_causes, substeps_metrics
from lnf.evaluation_cost import chunked_energy, FRAME_BLOCK_BYTES, decode_batch, frame_block
from lnf.tabulated import TABLE_OFF_BOX_WARN

log = logging.getLogger("lnf.evaluation")


@dataclass
class RolloutEvaluation:
    """Metrics plus the arrays behind them (n trajectories, T samples, N evaluation points); the fields only of the
    first k trajectories that :func:`evaluate_rollouts` was asked to keep (``keep_fields``; all by default)."""

    metrics: dict[str, float]
    times: np.ndarray  # (T,)
    q_pred: np.ndarray  # (n, T, d)
    q_ref: np.ndarray  # (n, T, d)
    pred_fields: np.ndarray  # (k, T, N, A), k ≤ n
    true_fields: np.ndarray  # (k, T, N, A)
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


def _may_tabulate(model: ReducedModel, decoding: str) -> bool:
    """Whether `decoding` lets evaluation try a table of φ for this model (``auto``: latent dimension ≤ 2)."""
    check_decoding(decoding)
    return decoding == "tabulated" or (decoding == "auto" and model.latent_dim <= 2)


def _table_box(model: ReducedModel, codes: Tensor, *more: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The box of a table of φ: the finite `codes` (…, d), the training codes' range where the model records one,
    and any `more` codes (see :func:`lnf.decoding_table.code_box`)."""
    ranges = [torch.stack([model.code_low, model.code_high])] if hasattr(model, "code_low") else []
    return code_box(codes, *ranges, *more)


def frame_decoder(model: ReducedModel, points: Tensor, decoding: str, codes: Tensor, field_dim: int,
                  frames: int) -> tuple[Callable[[Tensor], Tensor], dict[str, float]]:
    """The decoder of frames on `points` (N, dim_B) that :func:`evaluate_rollouts` uses, codes (B, d) → (B, N, A),
    and the metrics that say which it is (see its `decoding`). `codes` (…, d) are the rollout's (their finite rows and
    the training codes' range, where the model records one, make the table's box); `frames` is how many frames it
    will decode twice (predicted and projected), the most a table may cost."""
    def exact(q: Tensor) -> Tensor:
        return model.decode(q, points)

    if not _may_tabulate(model, decoding) or model.state_is_field:
        return exact, {"decoding_tabulated": 0.0}
    low, high = _table_box(model, codes)
    table = DecodingTable.build(exact, low, high, model.reference_tensor(), len(points), field_dim,
                                budget=frames if decoding == "auto" else None)
    if table is None:
        if decoding == "tabulated":
            log.warning("decoding=tabulated: no Chebyshev table meets its tolerance on these points (see the "
                        "message above); the frames are decoded exactly")
        return exact, {"decoding_tabulated": 0.0}
    log.info("decoding through a Chebyshev table in the codes: %d nodes per axis on [%s .. %s], error %.2g of the "
             "largest field, built in %.2f s", table.n, ", ".join(f"{v:.4g}" for v in low),
             ", ".join(f"{v:.4g}" for v in high), table.error, table.info["decoding_table_seconds"])
    return table, {"decoding_tabulated": 1.0, **{k: float(v) for k, v in table.info.items()}}


def frame_reducer(model: ReducedModel, points: Tensor, decoding: str, codes: Tensor, field_dim: int,
                  frames: int) -> tuple[Callable[[Tensor], Tensor], dict[str, float]]:
    """ρ̃ of the true frames on the reduction points `points` (N_r, dim_B), values (B, N_r, A) → codes (B, d), and
    the metrics that say how: where `decoding` tabulates and the model's K steps iterate on φ
    (``reduces_through_field``), they read φ and ∂φ/∂q̃ from a Chebyshev table on these points (its box also holds
    the reduction's start codes; the exact jet outside it), else the model's own reduce()."""
    def exact(values: Tensor) -> Tensor:
        return model.reduce(points, values)

    if not _may_tabulate(model, decoding) or not model.reduces_through_field:
        return exact, {"reduction_tabulated": 0.0}
    starts = getattr(model, "starts", None)
    low, high = _table_box(model, codes, *([starts] if starts is not None else []))

    def exact_jet(q: Tensor) -> tuple[Tensor, Tensor]:
        jet = model.field.jet(q, points, order=1)
        return jet.value, jet.J

    # the K steps of every frame: a table that costs fewer jets than they do
    table = DecodingTable.build(lambda q: model.decode(q, points), low, high, model.reference_tensor(), len(points),
                                field_dim, jacobian=lambda q: exact_jet(q)[1],
                                budget=frames * getattr(model, "reduction_steps", 1) if decoding == "auto" else None)
    if table is None:
        return exact, {"reduction_tabulated": 0.0}
    tabulated = TabulatedField(table, points, exact_jet)
    log.info("reducing the true frames through a Chebyshev table of φ and ∂φ/∂q̃ on the %d reduction points: %d "
             "nodes per axis, error %.2g", len(points), table.n, table.error)

    def reduce(values: Tensor) -> Tensor:
        return model.reduce(points, values, field=tabulated)

    return reduce, {"reduction_tabulated": 1.0, "reduction_table_nodes": float(table.n),
                    "reduction_table_error": float(table.error),
                    "reduction_table_seconds": float(table.info["decoding_table_seconds"])}


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
    keep_fields: Optional[int] = None,
    block_bytes: int = FRAME_BLOCK_BYTES,
    progress: bool = False,
    decoding: str = "auto",
) -> RolloutEvaluation:
    """Roll out every trajectory of full-order `states` (n, T, S) sampled at `times` (T,) [s].

    `points` (N, dim_B) are the evaluation points (equal quadrature weights |B|/N); the true fields there
    come from `true_fields`/`true_velocities` (n, T, N, A) when given, else from the scene. Decoding and
    errors use all N points; ρ̃ (initial conditions and the projected reference q̃_ref) uses an evenly
    strided subset of at most `max_reduction_points` of them (see :func:`reduction_subset`).

    Memory stays bounded: the frames are decoded, projected and compared a block at a time (at most `block_bytes`
    of float64 true fields per block, :func:`frame_block`; batches of `snapshot_chunk` frames, fewer on many
    points, :func:`decode_batch`), the true fields of the scene are computed block by
    block too, and the metrics are reduced from each frame's weighted sums; only the first `keep_fields`
    trajectories (default: all) keep their predicted and true fields in the result (``pred_fields``,
    ``true_fields``, e.g. for Figure 3). The metrics do not depend on the blocks. `progress` shows a progress bar
    over the decoded frames (not inside a Lightning run, which has its own).

    `decoding`: ``exact`` passes every frame through φ; ``tabulated`` decodes through a Chebyshev table of φ on
    the evaluation points in the codes (:class:`lnf.decoding_table.DecodingTable`, its measured error ≤ 1e-5 of
    the largest field, exact outside its box); ``auto`` (default) tabulates where it pays: latent dimension ≤ 2 and
    a table cheaper than the frames it replaces. The metrics say which was used (``decoding_tabulated``, and the
    table's ``decoding_table_nodes`` and ``decoding_table_error``); its build time counts as decoding time.

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
    n, T = states.shape[:2]
    dt = float(times[1] - times[0])
    pts = torch.as_tensor(points, dtype=p.dtype, device=p.device)
    if model.state_is_field:
        max_reduction_points = None  # the full-order model takes the whole field as its state
    sub = reduction_subset(len(points), grid_shape, max_reduction_points)
    pts_r = pts[torch.as_tensor(sub, device=p.device)]
    stored = true_fields is not None and true_velocities is not None
    if stored:  # (n, T, N, A) arrays: read a block of frames at a time (a view, no copy)
        true_fields = np.asarray(true_fields)
        fields0 = np.asarray(true_fields[:, 0])[:, sub]
        vel0_np = np.asarray(np.asarray(true_velocities)[:, 0])[:, sub]
    else:  # the scene's fields: at t0 on the reduction subset now, on all points block by block below
        fields0, vel0_np = (a[:, 0] for a in reference_fields(scene, states[:, :1], points[sub], label))
    field_dim = int(np.shape(fields0)[-1])

    q0 = model.reduce(pts_r, torch.as_tensor(fields0, dtype=p.dtype, device=p.device))
    v0 = model.project_velocity(q0, pts_r, torch.as_tensor(vel0_np, dtype=p.dtype, device=p.device))
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
        if table_info["table_fallback_fraction"] > TABLE_OFF_BOX_WARN:
            log.warning("%s: %s", label, dynamics.off_box_text(traj.q, table_info["table_fallback_fraction"]))

    if weights is None:
        weights = np.full(points.shape[0], 1.0 / points.shape[0])
    else:
        weights = np.asarray(weights, dtype=np.float64) / float(np.sum(weights))
    d = model.latent_dim
    frames = n * T
    flat_q = traj.q.reshape(frames, d)
    finite = torch.isfinite(flat_q).all(-1)
    safe_q = torch.where(finite[:, None], flat_q, torch.zeros_like(flat_q))
    flat_true = true_fields.reshape(frames, *true_fields.shape[2:]) if stored else None
    flat_states = None if stored else np.asarray(states).reshape(frames, *np.shape(states)[2:])
    keep = n if keep_fields is None else min(max(int(keep_fields), 0), n)
    pred_kept = np.empty((keep, T, len(points), field_dim))
    true_kept = np.empty((keep, T, len(points), field_dim))
    err = np.empty(frames)  # Σ_j w_j ‖pred − true‖² per frame
    proj_err = np.empty(frames)  # Σ_j w_j ‖proj − true‖²
    ref = np.empty(frames)  # Σ_j w_j ‖true‖²
    q_ref = torch.empty(frames, d, dtype=p.dtype, device=p.device)
    chunk = decode_batch(len(points), snapshot_chunk)
    block = frame_block(len(points), field_dim, chunk, block_bytes)  # a multiple of chunk: the same batches
    tick = time.perf_counter()
    decode, decoding_info = frame_decoder(model, pts, decoding, flat_q, field_dim, frames)
    decode_seconds = time.perf_counter() - tick
    reduce_frames, reduction_info = frame_reducer(model, pts_r, decoding, flat_q, field_dim, frames)
    with progress_bar(progress, frames, f"decoding the {label}") as advance:
        for k0 in range(0, frames, block):
            k1 = min(k0 + block, frames)
            if stored:
                truth = np.asarray(flat_true[k0:k1], dtype=np.float64)
                truth_r = np.asarray(flat_true[k0:k1][:, sub])
            else:
                truth = np.asarray(scene.fields(flat_states[k0:k1], points)[0], dtype=np.float64)
                truth_r = truth[:, sub]
            truth_r = torch.as_tensor(truth_r, dtype=p.dtype, device=p.device)
            pred = torch.empty((k1 - k0, len(points), field_dim), dtype=p.dtype, device=p.device)
            proj = torch.empty_like(pred)
            for c0 in range(k0, k1, chunk):
                c1 = min(c0 + chunk, k1)
                tick = time.perf_counter()
                alive = finite[c0:c1]
                if bool(alive.all()):
                    pred[c0 - k0:c1 - k0] = decode(safe_q[c0:c1])
                else:  # frames after a divergence are NaN: not decoded
                    pred[c0 - k0:c1 - k0] = float("nan")
                    if bool(alive.any()):
                        pred[c0 - k0:c1 - k0][alive] = decode(safe_q[c0:c1][alive])
                decode_seconds += time.perf_counter() - tick
                q_ref[c0:c1] = reduce_frames(truth_r[c0 - k0:c1 - k0])
                proj[c0 - k0:c1 - k0] = decode(q_ref[c0:c1])
                advance(c1 - c0)
            pred_np, proj_np = pred.double().cpu().numpy(), proj.double().cpu().numpy()
            err[k0:k1] = M.frame_sq(pred_np - truth, weights)
            proj_err[k0:k1] = M.frame_sq(proj_np - truth, weights)
            ref[k0:k1] = M.frame_sq(truth, weights)
            for i in range(k0 // T, min((k1 - 1) // T + 1, keep)):  # the kept trajectories' frames in this block
                a, b = max(k0, i * T), min(k1, (i + 1) * T)
                pred_kept[i, a - i * T:b - i * T] = pred_np[a - k0:b - k0]
                true_kept[i, a - i * T:b - i * T] = truth[a - k0:b - k0]
            del truth, truth_r, pred, proj, pred_np, proj_np

    kin, pot = chunked_energy(model, torch.where(finite[:, None], flat_q, 0.0),
                              torch.where(finite[:, None], traj.v.reshape(frames, d), 0.0), quadrature)
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

    err, proj_err, ref = err.reshape(n, T), proj_err.reshape(n, T), ref.reshape(n, T)
    metrics: dict[str, float] = {}
    metrics.update(M.field_metrics_from_sums("field_rel_l2", err, ref, times, train_horizon))
    metrics.update(M.field_metrics_from_sums("projection_rel_l2", proj_err, ref, times, train_horizon))
    q_pred_np = traj.q.double().cpu().numpy()
    q_ref_np = q_ref.reshape(n, T, d).double().cpu().numpy()
    metrics.update(M.latent_rmse(q_pred_np, q_ref_np))
    if true_energies is not None:
        metrics.update(M.energy_metrics(kin + pot, kin_true + pot_true, scene.energy_scale))
    vpt = M.valid_prediction_time_from_sums(err, ref, float(weights.sum()), times)
    metrics.update({f"vpt/{k}": v for k, v in M.summarize(vpt).items()})
    metrics["vpt/median"] = float(np.median(vpt))
    metrics["vpt/min"] = float(np.min(vpt))
    metrics.pop("vpt/max", None)
    diverged = divergence_steps(traj.diverged_step, ~np.isfinite(kin + pot))
    metrics.update(divergence_metrics(diverged, dt, float(times[0]), label=label, causes=initial_state_causes(
        model, dynamics, q0, v0, np.flatnonzero(diverged >= 0), quadrature),
        diagnoses=traj.extra.get("divergence_causes")))
    metrics.update(substeps_metrics(traj, dt, label))
    metrics["rollout_seconds_per_trajectory"] = rollout_seconds / n
    metrics["rollout_seconds_per_step"] = rollout_seconds / max(T - 1, 1)
    metrics["decode_seconds_per_trajectory"] = decode_seconds / n  # all T frames on the N evaluation points
    metrics["frames"] = float(T)
    metrics["evaluation_points"] = float(len(points))
    metrics["fields_seconds_per_trajectory"] = (rollout_seconds + decode_seconds) / n  # rollout + decoding
    metrics.update(decoding_info)
    metrics.update(reduction_info)
    for key in ("table_nodes", "table_points", "table_terms", "table_error", "table_seconds",
                "table_fallback_fraction"):  # offline cost of a tabulated dynamics
        if key in table_info:
            metrics[key] = float(table_info[key])
    return RolloutEvaluation(
        metrics=metrics, times=np.asarray(times), q_pred=q_pred_np, q_ref=q_ref_np, pred_fields=pred_kept,
        true_fields=true_kept, points=np.asarray(points),
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
    progress: bool = False,
) -> dict[str, float]:
    """energy_drift = max_t |Ẽ(t) − Ẽ(0)| / E_scale over a `steps`-step rollout from full-order states (n, S).

    `progress` shows a progress bar over the steps (not inside a Lightning run).

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
    with progress_bar(progress, int(steps), f"long-horizon check ({len(q0)} trajectories)", "steps") as advance:
        traj = model.rollout(q0, v0, dt=dt, steps=steps, integrator=integrator, quadrature=quadrature,
                             record_every=record_every, on_divergence="mark",
                             controls=trajectory_controls(scene, states0, q0) if controls is None else
                             torch.as_tensor(np.asarray(controls), dtype=q0.dtype, device=q0.device),
                             progress=advance if progress else None)
    seconds = time.perf_counter() - start
    shape = traj.q.shape[:-1]
    kin, pot = chunked_energy(model, torch.nan_to_num(traj.q).reshape(-1, traj.q.shape[-1]),
                              torch.nan_to_num(traj.v).reshape(-1, traj.v.shape[-1]), quadrature)
    energy = (kin + pot).reshape(shape).double().cpu().numpy()
    diverged = divergence_steps(traj.diverged_step, ~np.isfinite(energy), record_every)
    energy[diverged >= 0] = np.nan
    drift = np.max(np.abs(energy - energy[:, :1]), axis=-1) / scene.energy_scale
    out = {f"energy_drift_long/{k}": v for k, v in M.summarize(drift).items()}
    out["energy_drift_long/steps"] = float(steps)
    out["energy_drift_long/seconds"] = seconds
    out.update(divergence_metrics(diverged, dt, suffix="_long", label="long-horizon energy check",
                                  causes=initial_state_causes(model, model.dynamics(quadrature) if
                                                              (diverged >= 0).any() else None, q0, v0,
                                                              np.flatnonzero(diverged >= 0), quadrature),
                                  diagnoses=traj.extra.get("divergence_causes")))
    out.update(substeps_metrics(traj, dt, "long-horizon energy check", suffix="_long"))
    return out


