"""Validation of the arrays a figure is given: clear errors naming the argument and the shape expected."""
from __future__ import annotations

import numpy as np


# --------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------


def _as_float_array(x, name: str) -> np.ndarray:
    try:
        arr = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array, got {type(x).__name__}") from exc
    return arr


def _check_times(times, name: str = "times", increasing: bool = True) -> np.ndarray:
    t = _as_float_array(times, name)
    letter = "T" if name == "times" else "S"
    if t.ndim != 1 or t.shape[0] < 1:
        raise ValueError(f"{name} must have shape ({letter},) with {letter} >= 1, got {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name} must be finite")
    if increasing and t.shape[0] > 1 and not np.all(np.diff(t) > 0):
        raise ValueError(f"{name} must be strictly increasing")
    return t


def _check_scalar(x, name: str) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real number, got {x!r}") from exc
    if not np.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


def _check_latent(q, name: str, T: int, d: int | None = None) -> np.ndarray:
    """(T, d) array; a 1-D array of length T is accepted as d = 1."""
    arr = _as_float_array(q, name)
    if arr.ndim == 1 and arr.shape[0] == T:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[0] != T or arr.shape[1] < 1:
        raise ValueError(f"{name} must have shape (T, d) with T = len(times) = {T}, got {arr.shape}")
    if d is not None and arr.shape[1] != d:
        raise ValueError(
            f"{name} must have shape (T, d) = ({T}, {d}) to match q_pred, got {arr.shape}"
        )
    return arr


def _check_series(x, name: str, T: int) -> np.ndarray:
    arr = _as_float_array(x, name)
    if arr.shape != (T,):
        raise ValueError(f"{name} must have shape (T,) with T = len(times) = {T}, got {arr.shape}")
    return arr


def _check_grid_shape(grid_shape) -> tuple[int, int]:
    try:
        gs = tuple(int(n) for n in grid_shape)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"grid_shape must be a pair of positive ints (nx, ny), got {grid_shape!r}") from exc
    if len(gs) != 2 or min(gs) < 1 or any(int(a) != a for a in grid_shape):
        raise ValueError(f"grid_shape must be a pair of positive ints (nx, ny), got {grid_shape!r}")
    return gs  # type: ignore[return-value]


def _check_grid_shape_nd(grid_shape) -> tuple[int, ...]:
    """1 to 3 positive ints: the evaluation grid of a 1-D, 2-D or 3-D body."""
    try:
        gs = tuple(int(n) for n in grid_shape)
        whole = all(int(a) == a for a in grid_shape)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"grid_shape must be 1 to 3 positive ints (points per axis), got {grid_shape!r}") from exc
    if not 1 <= len(gs) <= 3 or min(gs) < 1 or not whole:
        raise ValueError(f"grid_shape must be 1 to 3 positive ints (points per axis), got {grid_shape!r}")
    return gs


def _check_box(bounds, dim: int, of: str = "the grid") -> np.ndarray:
    """[[lo, hi], ...] of a `dim`-dimensional body as a (dim, 2) array with lo < hi."""
    arr = _as_float_array(bounds, "bounds").reshape(-1)
    if arr.shape != (2 * dim,) or not np.all(np.isfinite(arr)) or not np.all(arr[1::2] > arr[0::2]):
        raise ValueError(f"bounds must be [[lo, hi], ...] with lo < hi for each of the {dim} axes of {of}, "
                         f"got {np.asarray(bounds).tolist()}")
    return arr.reshape(dim, 2)


def _check_bounds(bounds) -> tuple[float, float, float, float]:
    """Accept ((xmin, xmax), (ymin, ymax)) or (xmin, xmax, ymin, ymax); return imshow extent."""
    arr = _as_float_array(bounds, "bounds").reshape(-1)
    if arr.shape != (4,):
        raise ValueError(
            "bounds must be ((xmin, xmax), (ymin, ymax)) or (xmin, xmax, ymin, ymax), "
            f"got {np.shape(bounds)}"
        )
    xmin, xmax, ymin, ymax = (float(v) for v in arr)
    if not (np.all(np.isfinite(arr)) and xmax > xmin and ymax > ymin):
        raise ValueError(f"bounds must be finite with xmin < xmax and ymin < ymax, got {arr.tolist()}")
    return xmin, xmax, ymin, ymax


def _check_fields(x, name: str, S: int, nf: int, s_label: str, nf_label: str = "Nf = prod(grid_shape)") -> np.ndarray:
    arr = _as_float_array(x, name)
    if arr.shape != (S, nf):
        n_sym = nf_label.split(" ", 1)[0]
        raise ValueError(
            f"{name} must have shape ({s_label}, {n_sym}) = ({S}, {nf}) with {nf_label}, got {arr.shape}"
        )
    return arr


def _check_points(points) -> np.ndarray:
    """(N, dim_B) evaluation points with 1 <= dim_B <= 3 and N >= 1, all finite; (N,) means dim_B = 1."""
    arr = _as_float_array(points, "points")
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[0] < 1 or not 1 <= arr.shape[1] <= 3:
        raise ValueError(f"points must have shape (N, dim_B) with N >= 1 and dim_B in 1..3, got {np.shape(points)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("points must be finite")
    return arr


# --------------------------------------------------------------------------------------
# small numeric helpers
# --------------------------------------------------------------------------------------
