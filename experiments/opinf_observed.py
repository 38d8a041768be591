"""Operator Inference given only lnf's sparse observations ("OpInf (observed)"), through gappy POD.

`evaluate()` of experiments/operator_inference.py fits OpInf on the full fine-grid fields; `evaluate_observed`
reads what lnf reads, the masked coarse observations (each trajectory: its fixed `masks` subset of the coarse
points), and is scored exactly as `evaluate()` is (lnf.metrics.field_metrics on the fine points, same weights and
horizon):

* training: the observed coarse fields and velocities of the training and validation trajectories (samples
  k < train_times; both are data lnf has when it trains, no test data) are completed together by
  :func:`lnf.baselines.gappy_pod.complete_snapshots` (snapshots [q, s q̇], s the ratio of the observed values'
  spreads; its rank cross-validated on held-out observations; points no trajectory observes interpolated from
  the others); :class:`OperatorInference` is fitted on the completed training trajectories, its form and λ chosen on
  the completed validation ones. POD weights: the fine points' mass weights carried to the coarse points through
  the interpolation (Pᵀ w: the quadrature of the interpolant), so the POD inner product is the fine one's.
* test: the initial reduced state is the gappy projection of the test trajectory's observed coarse points at t=0
  (weighted least squares on the basis rows there); the rollout's coarse fields go to the fine points through
  :func:`lnf.baselines.gappy_pod.interpolation_matrix`.

Relies on these attributes of a fitted OperatorInference: ``basis.entries`` (D, r) with D = 2·Nc·A ordered
[q, σ q̇] point-major (index p·A + a), ``mean`` (D,), ``sigma``, ``scale``, ``shape``, and ``_predict_from``.
`projection_rel_l2`: the basis' best (orthogonal projection of the full coarse test fields, interpolated);
`gappy_projection_rel_l2`: the gappy projection of every test sample from its observed points.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from experiments.operator_inference import ERR, mass_weights, split_controls

COMPLETION_RANKS = (1, 2, 3, 4, 6, 8)  # candidates of the completion's rank


def to_fine(P: Any, x: np.ndarray) -> np.ndarray:
    """(n, T, Nc, A) → (n, T, Nf, A) through the sparse interpolation matrix P (Nf, Nc)."""
    n, T, Nc, A = x.shape
    flat = x.transpose(2, 0, 1, 3).reshape(Nc, -1)
    y = P @ np.nan_to_num(flat, nan=0.0)
    y[:, ~np.isfinite(flat).all(0)] = np.nan  # a diverged sample stays NaN
    return y.reshape(-1, n, T, A).transpose(1, 2, 0, 3)


@dataclass
class Completion:
    """lnf's training and validation observations completed by gappy POD, shared by every OpInf rank fitted on them.

    fields, velocities: (n_train + n_val, train_times, Nc, A) completed coarse samples; P (Nf, Nc) the coarse → fine
    interpolation; mass (Nc,) POD weights; point_weights (Nf,) the fine points' quadrature weights (uniform where the
    file has none) and metric_weights (Nc,) their share on the coarse points; rank, errors (the cross-validation's, or None),
    info (of :func:`complete_snapshots`), seconds (the completion with its rank selection)."""

    fields: np.ndarray
    velocities: np.ndarray
    P: Any
    mass: np.ndarray
    point_weights: np.ndarray
    metric_weights: np.ndarray
    rank: int
    errors: Optional[dict[int, float]]
    info: dict[str, Any]
    seconds: float


def complete_observations(scene: Any, splits: dict[str, Any], completion_rank: Optional[int] = None,
                          iterations: int = 500, tol: float = 1e-6, cv_iterations: int = 40) -> Completion:
    """Complete the observed coarse samples k < train_times of the training and validation trajectories at
    `completion_rank` (None: the one of COMPLETION_RANKS with the smallest error on held-out observations, each
    candidate given at most `cv_iterations` sweeps)."""
    from lnf.baselines.gappy_pod import complete_snapshots, interpolation_matrix, select_rank

    train, val = splits["train"], splits["val"]
    K, test = train.train_times, splits["test"]
    start = time.perf_counter()
    P = interpolation_matrix(train.coarse_points, train.fine_points)
    mass = np.asarray(P.T @ mass_weights(scene, train))
    mass = np.maximum(mass, 1e-6 * mass.max())  # a coarse point no fine point reads still counts, a little
    Nf = test.fields.shape[2]
    qw = np.full(Nf, 1.0 / Nf) if test.weights is None else np.asarray(test.weights, dtype=np.float64)
    metric_weights = np.maximum(np.asarray(P.T @ qw), 1e-12)
    masks = np.concatenate([train.masks, val.masks]).astype(bool)
    q = np.concatenate([train.coarse_fields[:, :K], val.coarse_fields[:, :K]]).astype(np.float64)
    v = np.concatenate([train.coarse_velocities[:, :K], val.coarse_velocities[:, :K]]).astype(np.float64)
    spread = [np.std(x[np.broadcast_to(masks[:, None, :, None], x.shape)]) for x in (q, v)]
    s = spread[0] / spread[1] if spread[0] > 0 and spread[1] > 0 else 1.0
    A = q.shape[-1]
    joint, options = np.concatenate([q, s * v], -1), dict(tol=tol, points=train.coarse_points)
    errors = None
    if completion_rank is None:  # cross-validated on held-out observations
        ranks = [r for r in COMPLETION_RANKS if r <= min(2 * A * masks.shape[1], len(masks) * K)]
        completion_rank, errors = select_rank(joint, masks, ranks, iterations=min(iterations, cv_iterations),
                                              **options)
    done, info = complete_snapshots(joint, masks, completion_rank, iterations=iterations, **options)
    return Completion(done[..., :A], done[..., A:] / s, P, mass, qw, metric_weights, int(completion_rank), errors, info,
                      time.perf_counter() - start)


def evaluate_observed(scene: Any, splits: dict[str, Any], rank: int, completion_rank: Optional[int] = None,
                      iterations: int = 500, tol: float = 1e-6, completion: Optional[Completion] = None
                      ) -> dict[str, Any]:
    """Fit OpInf at `rank` on the gappy-completed observations (`completion`, or computed here at
    `completion_rank`, see :func:`complete_observations`), roll out the test split from its observed initial points,
    score it on the fine points. The splits share their coarse and fine points. fit_seconds includes the completion
    (completion_seconds, with the rank's selection; a completion shared by several ranks counts in each);
    decode_seconds: the decoding of the reduced rollout and its interpolation to the fine points."""
    from lnf import metrics as M
    from lnf.baselines.gappy_pod import gappy_encode
    from lnf.baselines.operator_inference import OperatorInference

    if completion is None:
        completion = complete_observations(scene, splits, completion_rank, iterations, tol)
    train, val, test = splits["train"], splits["val"], splits["test"]
    T, K, n_tr, A = len(test.times), train.train_times, len(train.masks), test.coarse_fields.shape[-1]
    P, mass, metric_weights, info = completion.P, completion.mass, completion.metric_weights, completion.info
    cq, cv, qw = completion.fields, completion.velocities, completion.point_weights
    start = time.perf_counter()
    model = OperatorInference(rank).fit(cq[:n_tr], cv[:n_tr], K, cq[n_tr:], cv[n_tr:], point_weights=mass,
                                        metric_weights=metric_weights, controls=split_controls(scene, train),
                                        val_controls=split_controls(scene, val))
    fit_seconds = completion.seconds + (time.perf_counter() - start)  # the completion is part of the fit

    def gappy_states(i: int, fields: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """Reduced states (T', r) of trajectory i's samples (T', Nc, A) from its observed points only."""
        x = np.concatenate([fields.reshape(len(fields), -1), model.sigma * velocities.reshape(len(fields), -1)], 1)
        obs = np.tile(np.repeat(np.asarray(test.masks[i], bool), A), 2)
        w = np.tile(np.repeat(mass, A), 2)
        return gappy_encode(model.basis.entries, model.mean, x, obs, w) / model.scale

    cf, cvel = np.asarray(test.coarse_fields, np.float64), np.asarray(test.coarse_velocities, np.float64)
    states0 = np.stack([gappy_states(i, cf[i, :1], cvel[i, :1])[0] for i in range(len(cf))])
    t0 = time.perf_counter()
    pred = model._predict_from(states0, T, split_controls(scene, test))
    fields, velocities = to_fine(P, pred.fields), to_fine(P, pred.velocities)
    decode_seconds = (time.perf_counter() - t0 - pred.rollout_seconds.sum()) / len(cf)
    weights = qw / qw.sum()
    times = np.asarray(test.times, dtype=np.float64)
    horizon = float(times[K]) if K < T else float(times[-1])  # as lnf's evaluation callback sets it
    true = np.asarray(test.fields, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        out: dict[str, Any] = dict(M.field_metrics(ERR, fields, true, weights, times, horizon))
        out.update(M.field_metrics("velocity_rel_l2", velocities, np.asarray(test.velocities, dtype=np.float64),
                                   weights, times, horizon))
        proj = to_fine(P, model.decode(model.encode(cf, cvel))[0])
        out.update(M.field_metrics("projection_rel_l2", proj, true, weights, times, horizon))
        gappy = np.stack([model.decode(gappy_states(i, cf[i], cvel[i]))[0] for i in range(len(cf))])
        out.update(M.field_metrics("gappy_projection_rel_l2", to_fine(P, gappy), true, weights, times, horizon))
    record = model.describe()
    out.update(method="OpInf (observed)", rank=rank, operators=record["operators"],
               regularizer=record["regularizer"], val_error=record["val_error"],
               velocity_weight=record["velocity_weight"], diverged=int(pred.diverged.sum()),
               trajectories=int(len(pred.diverged)), fit_seconds=fit_seconds, completion_seconds=completion.seconds,
               completion_rank=completion.rank, completion_errors=completion.errors,
               completion_iterations=info["iterations"], completion_converged=info["converged"],
               unobserved_points=info["unobserved_points"],
               observed_fraction=float(np.concatenate([train.masks, val.masks]).mean()),
               rollout_seconds_per_trajectory=float(np.mean(pred.rollout_seconds)),
               decode_seconds_per_trajectory=float(decode_seconds), frames=T,
               fields_seconds_per_trajectory=float(np.mean(pred.rollout_seconds) + decode_seconds),
               candidates=record["candidates"])
    return out
