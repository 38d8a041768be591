"""Test metrics of docs/method.md §7.3. Arrays: fields (n, T, N, A), weights (N,), times (T,), energies (n, T)."""
from __future__ import annotations

import numpy as np


def _weighted_sq(x: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Σ_j w_j ‖x_j‖² per (trajectory, time): (n, T)."""
    return np.einsum("itja,j->it", x * x, weights)


def field_rel_l2(pred: np.ndarray, true: np.ndarray, weights: np.ndarray, window: np.ndarray) -> np.ndarray:
    """sqrt(Σ_t Σ_j w_j ‖pred − true‖² / Σ_t Σ_j w_j ‖true‖²) over the time samples in `window` (T,) bool: (n,)."""
    err = _weighted_sq(pred - true, weights)[:, window].sum(-1)
    ref = _weighted_sq(true, weights)[:, window].sum(-1)
    return np.sqrt(err / np.maximum(ref, np.finfo(np.float64).tiny))


def valid_prediction_time(pred: np.ndarray, true: np.ndarray, weights: np.ndarray, times: np.ndarray,
                          threshold: float = 0.025) -> np.ndarray:
    """First t where the frame MSE / the trajectory's mean squared true field exceeds `threshold` (n,).

    The horizon (last time + one step) if never; NaN frames (a diverged rollout) count as exceeding.
    """
    frame = _weighted_sq(pred - true, weights) / weights.sum()
    scale = (_weighted_sq(true, weights) / weights.sum()).mean(-1, keepdims=True)
    bad = ~(frame / np.maximum(scale, np.finfo(np.float64).tiny) <= threshold)
    horizon = times[-1] + (times[-1] - times[-2] if len(times) > 1 else 0.0)
    first = np.where(bad.any(-1), bad.argmax(-1), -1)
    return np.where(first >= 0, times[np.clip(first, 0, None)], horizon)


def summarize(values: np.ndarray) -> dict[str, float]:
    """median and max over trajectories; NaN (diverged) counts as +inf for the max."""
    v = np.where(np.isnan(values), np.inf, values)
    return {"median": float(np.median(v)), "max": float(np.max(v))}


def time_windows(times: np.ndarray, train_horizon: float) -> dict[str, np.ndarray]:
    """Boolean masks of the docs/method.md §7.3 windows: all, in_horizon (t < horizon), extrapolation (t ≥ horizon)."""
    eps = 1e-9 * max(1.0, abs(train_horizon))
    return {"all": np.ones_like(times, dtype=bool), "in_horizon": times < train_horizon - eps,
            "extrapolation": times >= train_horizon - eps}


def field_metrics(name: str, pred: np.ndarray, true: np.ndarray, weights: np.ndarray, times: np.ndarray,
                  train_horizon: float) -> dict[str, float]:
    """`{name}/{window}/{median|max}` for each window that has samples."""
    out = {}
    for window, mask in time_windows(times, train_horizon).items():
        if mask.any():
            for stat, value in summarize(field_rel_l2(pred, true, weights, mask)).items():
                out[f"{name}/{window}/{stat}"] = value
    return out


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
