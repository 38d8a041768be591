"""Test metrics of docs/method.md §7.3. Arrays: fields (n, T, N, A), weights (N,), times (T,), energies (n, T).

Each field metric has one formula, on per-frame weighted sums (``*_from_sums``: what the streamed evaluation of
:mod:`lnf.evaluation` accumulates a block of frames at a time); the array forms compute those sums and call it."""
from __future__ import annotations

import numpy as np

VPT_THRESHOLD = 0.025  # frame MSE / the trajectory's mean squared true field beyond which a prediction is invalid


def frame_sq(x: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Σ_j w_j ‖x_j‖² per frame of x (…, N, A): (…)."""
    return np.einsum("...ja,j->...", x * x, weights)


def field_rel_l2_from_sums(err: np.ndarray, ref: np.ndarray, window: np.ndarray) -> np.ndarray:
    """sqrt(Σ_t err / Σ_t ref) over the samples in `window` (T,) bool, from per-frame sums (n, T): (n,)."""
    return np.sqrt(err[:, window].sum(-1) / np.maximum(ref[:, window].sum(-1), np.finfo(np.float64).tiny))


def field_rel_l2(pred: np.ndarray, true: np.ndarray, weights: np.ndarray, window: np.ndarray) -> np.ndarray:
    """sqrt(Σ_t Σ_j w_j ‖pred − true‖² / Σ_t Σ_j w_j ‖true‖²) over the time samples in `window` (T,) bool: (n,)."""
    return field_rel_l2_from_sums(frame_sq(pred - true, weights), frame_sq(true, weights), window)


def valid_prediction_time_from_sums(err: np.ndarray, ref: np.ndarray, weight_sum: float, times: np.ndarray,
                                    threshold: float = VPT_THRESHOLD) -> np.ndarray:
    """:func:`valid_prediction_time` from the per-frame sums `err` = Σ_j w_j ‖pred − true‖² and `ref` = Σ_j w_j
    ‖true‖² (n, T) and Σ_j w_j: (n,)."""
    frame = err / weight_sum
    scale = (ref / weight_sum).mean(-1, keepdims=True)
    bad = ~(frame / np.maximum(scale, np.finfo(np.float64).tiny) <= threshold)
    horizon = times[-1] + (times[-1] - times[-2] if len(times) > 1 else 0.0)
    first = np.where(bad.any(-1), bad.argmax(-1), -1)
    return np.where(first >= 0, times[np.clip(first, 0, None)], horizon)


def valid_prediction_time(pred: np.ndarray, true: np.ndarray, weights: np.ndarray, times: np.ndarray,
                          threshold: float = VPT_THRESHOLD) -> np.ndarray:
    """First t where the frame MSE / the trajectory's mean squared true field exceeds `threshold` (n,).

    The horizon (last time + one step) if never; NaN frames (a diverged rollout) count as exceeding.
    """
    return valid_prediction_time_from_sums(frame_sq(pred - true, weights), frame_sq(true, weights),
                                           float(weights.sum()), times, threshold)


def summarize(values: np.ndarray) -> dict[str, float]:
    """median and max over trajectories; NaN (diverged) counts as +inf for the max."""
    v = np.where(np.isnan(values), np.inf, values)
    return {"median": float(np.median(v)), "max": float(np.max(v))}


def time_windows(times: np.ndarray, train_horizon: float) -> dict[str, np.ndarray]:
    """Boolean masks of the docs/method.md §7.3 windows: all, in_horizon (t < horizon), extrapolation (t ≥ horizon)."""
    eps = 1e-9 * max(1.0, abs(train_horizon))
    return {"all": np.ones_like(times, dtype=bool), "in_horizon": times < train_horizon - eps,
            "extrapolation": times >= train_horizon - eps}


def field_metrics_from_sums(name: str, err: np.ndarray, ref: np.ndarray, times: np.ndarray,
                            train_horizon: float) -> dict[str, float]:
    """`{name}/{window}/{median|max}` for each window that has samples, from per-frame sums (n, T) (see
    :func:`field_rel_l2_from_sums`)."""
    out = {}
    for window, mask in time_windows(times, train_horizon).items():
        if mask.any():
            for stat, value in summarize(field_rel_l2_from_sums(err, ref, mask)).items():
                out[f"{name}/{window}/{stat}"] = value
    return out


def field_metrics(name: str, pred: np.ndarray, true: np.ndarray, weights: np.ndarray, times: np.ndarray,
                  train_horizon: float) -> dict[str, float]:
    """`{name}/{window}/{median|max}` for each window that has samples."""
    return field_metrics_from_sums(name, frame_sq(pred - true, weights), frame_sq(true, weights), times,
                                   train_horizon)


def energy_metrics(energy_pred: np.ndarray, energy_true: np.ndarray, energy_scale: float) -> dict[str, float]:
    """energy_rel_err = max_t |Ẽ − E_true| / E_scale; energy_drift = max_t |Ẽ(t) − Ẽ(0)| / E_scale."""
    rel = np.max(np.abs(energy_pred - energy_true), axis=-1) / energy_scale
    drift = np.max(np.abs(energy_pred - energy_pred[:, :1]), axis=-1) / energy_scale
    out = {f"energy_rel_err/{k}": v for k, v in summarize(rel).items()}
    out.update({f"energy_drift/{k}": v for k, v in summarize(drift).items()})
    return out


def latent_rmse(q_pred: np.ndarray, q_ref: np.ndarray) -> dict[str, float]:
    """RMS over time and latent dims of q̃(t) − q̃_ref(t), per trajectory: median/max."""
    return {f"latent_rmse/{k}": v for k, v in summarize(np.sqrt(np.mean((q_pred - q_ref) ** 2, axis=(1, 2)))).items()}
