"""Figures for the lifted-pendulum benchmark (the paper's Figure 3) and friends.

Pure functions of numpy arrays that return :class:`matplotlib.figure.Figure` objects.
Figures are built with ``Figure()`` directly, never through ``pyplot``: nothing needs a
display, no global figure registry fills up, and the process-wide backend is left alone
(PNG output goes through Agg regardless of the selected backend).

Public API
----------
- :func:`latent_and_energy_figure` -- latent q̃(t) predicted vs projected, energies predicted
  vs true, training horizon marked (Figure 3, top row).
- :func:`field_snapshots_figure` -- predicted field, true field and absolute error at a few
  times before/after the training horizon (Figure 3, bottom).
- :func:`figure3` -- both of the above in one figure, for a 1-, 2- or 3-D body, its fields given on a
  midpoint grid (``grid_shape``) or on scattered points (``points``: mesh nodes, random samples).
- :func:`default_snapshot_indices` -- evenly spaced sample indices on each side of the horizon.
- :func:`save_figure` -- atomic PNG write (200 dpi), with a vector PDF of the same stem beside it.

Non-finite values in predictions (a diverged rollout) are plotted, not hidden and not fatal:
lines get gaps, images show masked pixels (or triangles touching a non-finite point) in grey, colour
limits use the finite values only.

Colour scales. Fields use a diverging map symmetric about 0, its limit the largest |value| of the true
field (or the 99th percentile of |predicted| where that is larger); predicted values beyond it saturate
and the colour bar gets an arrow. Errors |pred − true| use a light-to-dark sequential map (small errors
light), its limit the 99th percentile of the finite errors, so that one outlier (a corner, a diverging
patch) does not turn the rest of the panel into a single colour; where errors exceed it the colour bar
gets an arrow (``extend="max"``).

Energies. The energy panel shows the total energy E = T + V predicted against true over the whole range
(its drift is what a long rollout is judged by); a third panel shows the kinetic/potential exchange, over
the whole range when the series oscillate a few times only, else in a window of a few periods around the
training horizon (shaded on the total-energy panel), so that a 20 s rollout is no solid band.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib  # noqa: F401  (no backend selection needed: no pyplot is used)
import numpy as np
from matplotlib.figure import Figure, SubFigure

__all__ = [
    "latent_and_energy_figure",
    "field_snapshots_figure",
    "figure3",
    "default_snapshot_indices",
    "save_figure",
    "vector_path",
    "ENERGY_KEYS",
]

ENERGY_KEYS = ("kinetic_pred", "potential_pred", "kinetic_true", "potential_true")

_FIELD_CMAP = "RdBu_r"
_ERROR_CMAP = "magma_r"  # sequential, light (small errors) to dark (large errors)
_MASK_COLOR = "0.6"  # grey for NaN/inf pixels
_HORIZON_STYLE = dict(color="0.35", linestyle=":", linewidth=1.2)
_DPI = 200
_ERROR_PERCENTILE = 99.0  # the error colour scale ends at this percentile of the finite errors
_MAX_PERIODS = 8  # more oscillations of the energies than this: kinetic/potential drawn in a window
_WINDOW_PERIODS = 4  # ... of this many periods around the training horizon
_ERROR_LABEL = "absolute error\n|pred − true|\n(field's units)"
_X_LABELS = ("X₁", "X₂", "X₃")  # body (material) coordinates


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


def _finite_absmax(*arrays: np.ndarray, default: float = 1.0) -> float:
    m = 0.0
    for a in arrays:
        fin = a[np.isfinite(a)]
        if fin.size:
            m = max(m, float(np.max(np.abs(fin))))
    return m if m > 0 else default


def _field_scale(pred: np.ndarray, true: np.ndarray) -> tuple[float, str]:
    """(vmax, extend) of the symmetric field colour scale [−vmax, vmax].

    vmax is the largest finite |true| value (the true field's peaks are data, never outliers), raised to the
    99th percentile of the finite |pred| values where the prediction is larger, and to the largest |pred| where
    that is at most 5 % more; a predicted value beyond it saturates and the colour bar gets an arrow on that
    side. Neither finite: 1."""
    fin_p = np.abs(pred[np.isfinite(pred)])
    vmax = _finite_absmax(true, default=0.0)
    if fin_p.size:
        vmax = max(vmax, float(np.percentile(fin_p, _ERROR_PERCENTILE)))
    if not vmax > 0:
        vmax = _finite_absmax(pred)
    lo = hi = False
    fin = pred[np.isfinite(pred)]
    if fin.size:
        top = float(np.max(np.abs(fin)))
        if top <= 1.05 * vmax:  # hardly beyond: widen the scale rather than clip
            vmax = max(vmax, top)
        lo, hi = bool(fin.min() < -vmax), bool(fin.max() > vmax)
    return vmax, {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}[(lo, hi)]


def _error_scale(err: np.ndarray) -> tuple[float, str]:
    """(vmax, extend) of the error colour scale [0, vmax]: the 99th percentile of the finite errors (the
    largest one where that is 0, 1 where there is none or all are 0). extend is "max" where some finite error
    lies above vmax (its pixels saturate), else "neither"."""
    fin = err[np.isfinite(err)]
    top = float(fin.max()) if fin.size else 0.0
    if not top > 0:
        return 1.0, "neither"
    vmax = float(np.percentile(fin, _ERROR_PERCENTILE))
    if not vmax > 0 or top <= vmax * 1.02:  # nothing (or hardly anything) to clip
        return top, "neither"
    return vmax, "max"


def _oscillation_window(times: np.ndarray, y: np.ndarray, h: float) -> tuple[float, float] | None:
    """A window of ``_WINDOW_PERIODS`` periods of ``y(t)`` around the training horizon ``h`` (moved inside the
    time range), or None when y oscillates at most ``_MAX_PERIODS`` times over the range (it is readable whole).
    Periods are counted from the crossings of y's median (finite samples only)."""
    fin = np.isfinite(y)
    if np.count_nonzero(fin) < 4 or times[-1] <= times[0]:
        return None
    s = np.sign(y[fin] - np.median(y[fin]))
    s = s[s != 0]
    periods = 0.5 * np.count_nonzero(s[1:] != s[:-1])
    if periods <= _MAX_PERIODS:
        return None
    t0, t1 = float(times[0]), float(times[-1])
    width = min(_WINDOW_PERIODS * (t1 - t0) / periods, t1 - t0)
    centre = min(max(h, t0 + width / 2), t1 - width / 2)
    a, b = (float(times[np.argmin(np.abs(times - v))]) for v in (centre - width / 2, centre + width / 2))
    return (a, b) if b > a else (centre - width / 2, centre + width / 2)  # edges on samples: round numbers


def _value_at(times: np.ndarray, y: np.ndarray, t0: float) -> float:
    """Linear interpolation of y(t) at t0 (NaN if a neighbouring sample is non-finite)."""
    if times.shape[0] == 1:
        return float(y[0])
    j = int(np.searchsorted(times, t0))
    j = min(max(j, 1), times.shape[0] - 1)
    t_a, t_b = times[j - 1], times[j]
    w = (t0 - t_a) / (t_b - t_a)
    if w <= 0.0:
        return float(y[j - 1])
    if w >= 1.0:
        return float(y[j])
    return float((1 - w) * y[j - 1] + w * y[j])


def _horizon_in_range(times: np.ndarray, h: float) -> bool:
    return bool(times[0] <= h <= times[-1])


def _format_t(t: float) -> str:
    return f"{t:.3g}"


# --------------------------------------------------------------------------------------
# drawing onto a (sub)figure
# --------------------------------------------------------------------------------------


def _mark_horizon(ax, times: np.ndarray, curves: list[tuple[np.ndarray, str]], h: float) -> None:
    if not _horizon_in_range(times, h):
        return
    ax.axvline(h, **_HORIZON_STYLE)
    for y, color in curves:
        v = _value_at(times, y, h)
        if np.isfinite(v):
            ax.plot([h], [v], marker="o", markersize=5, color=color, zorder=5, linestyle="none")


def _horizon_legend_handle():
    from matplotlib.lines import Line2D

    return Line2D([], [], marker="o", markersize=5, color="0.35", linestyle=":", label="training horizon")


def _plot_gappy(ax, times: np.ndarray, y: np.ndarray, **kwargs) -> None:
    """y(t) as a line with gaps where it is NaN; a finite sample between two gaps (the last one before a rollout
    diverged, say), which a line cannot show, as a dot."""
    ax.plot(times, y, **kwargs)
    fin = np.isfinite(y)
    alone = fin & ~np.concatenate([[False], fin[:-1]]) & ~np.concatenate([fin[1:], [False]])
    if alone.any():
        ax.plot(times[alone], y[alone], linestyle="none", marker="o", markersize=3.5, color=kwargs.get("color"))


def _legend_below(ax, handles, ncol: int) -> None:
    """The legend of ``ax`` under its x label (set that first), outside the data: it starts as far below the axes
    as the tick labels and the label reach, in points, whatever the axes' size (constrained layout makes room)."""
    import matplotlib as mpl
    from matplotlib.font_manager import FontProperties
    from matplotlib.transforms import offset_copy

    rc = mpl.rcParams
    size = lambda key: FontProperties(size=rc[key]).get_size_in_points()  # noqa: E731
    lines = ax.get_xlabel().count("\n") + 1 if ax.get_xlabel() else 0
    drop = (rc["xtick.major.size"] + rc["xtick.major.pad"] + 1.3 * size("xtick.labelsize")
            + (rc["axes.labelpad"] + 1.25 * size("axes.labelsize") * lines if lines else 0) + 3.0)
    below = offset_copy(ax.transAxes, fig=ax.get_figure(root=True), x=0.0, y=-drop, units="points")
    ax.legend(handles=handles, fontsize="small", loc="upper center", bbox_to_anchor=(0.5, 0.0), bbox_transform=below,
              borderaxespad=0.0, ncol=max(1, min(len(handles), ncol)), frameon=False, handlelength=2.2,
              columnspacing=1.2)


def _draw_latent_energy(
    fig: Figure | SubFigure,
    times: np.ndarray,
    q_pred: np.ndarray,
    q_proj: np.ndarray,
    kin_pred: np.ndarray,
    pot_pred: np.ndarray,
    kin_true: np.ndarray,
    pot_true: np.ndarray,
    h: float,
) -> tuple:
    """Three panels: latent q̃(t); total energy predicted vs true over the whole range; the kinetic/potential
    exchange, whole or (when it oscillates more than ``_MAX_PERIODS`` times) in a window of a few periods around
    the training horizon, the window shaded on the total-energy panel."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    # non-finite values (a diverged rollout) become gaps in the lines
    q_pred, q_proj, kin_pred, pot_pred, kin_true, pot_true = (
        np.where(np.isfinite(a), a, np.nan) for a in (q_pred, q_proj, kin_pred, pot_pred, kin_true, pot_true)
    )
    ax_q, ax_e, ax_x = fig.subplots(1, 3, width_ratios=[1.25, 1.0, 1.0])
    d = q_pred.shape[1]
    colors = [f"C{i % 10}" for i in range(d)]
    has_h = _horizon_in_range(times, h)
    t_hi = times[-1] if times[-1] > times[0] else times[0] + 1.0

    # left: latent coordinates
    handles = []
    for i in range(d):
        lbl = "q̃" if d == 1 else f"q̃{_subscript(i + 1)}"
        _plot_gappy(ax_q, times, q_pred[:, i], color=colors[i], linestyle="-", linewidth=1.5)
        _plot_gappy(ax_q, times, q_proj[:, i], color=colors[i], linestyle="--", linewidth=1.3)
        handles.append(Line2D([], [], color=colors[i], linestyle="-", label=f"{lbl} predicted"))
        handles.append(Line2D([], [], color=colors[i], linestyle="--", label=f"{lbl} projected"))
    _mark_horizon(ax_q, times, [(q_pred[:, i], colors[i]) for i in range(d)], h)
    if has_h:
        handles.append(_horizon_legend_handle())
    ax_q.set_xlabel("time t [s]")
    ax_q.set_ylabel("latent coordinate q̃" if d == 1 else "latent coordinates q̃ᵢ")
    ax_q.set_title("latent coordinates")
    _legend_below(ax_q, handles, 2 if d > 1 else 3)

    # middle: total energy over the whole range
    c_tot, c_kin, c_pot = "k", "C3", "C0"
    tot_pred, tot_true = kin_pred + pot_pred, kin_true + pot_true
    _plot_gappy(ax_e, times, tot_true, color="0.55", linestyle="--", linewidth=1.6)
    _plot_gappy(ax_e, times, tot_pred, color=c_tot, linestyle="-", linewidth=1.3)
    _mark_horizon(ax_e, times, [(tot_pred, c_tot)], h)
    e_handles = [Line2D([], [], color=c_tot, linestyle="-", label="predicted"),
                 Line2D([], [], color="0.55", linestyle="--", label="true")]
    window = _oscillation_window(times, kin_true if np.isfinite(kin_true).sum() >= 4 else kin_pred, h)
    if window is not None:
        ax_e.axvspan(*window, color="C1", alpha=0.12, linewidth=0)
        e_handles.append(Patch(color="C1", alpha=0.25, label="window of the right panel"))
    if has_h:
        e_handles.append(_horizon_legend_handle())
    ax_e.set_xlabel("time t [s]")
    ax_e.set_ylabel("total energy T + V [J]")
    ax_e.set_title("total energy")
    _legend_below(ax_e, e_handles, 2)

    # right: kinetic / potential exchange (a window of it on long horizons)
    _plot_gappy(ax_x, times, kin_true, color=c_kin, linestyle="--", linewidth=1.3)
    _plot_gappy(ax_x, times, kin_pred, color=c_kin, linestyle="-", linewidth=1.5)
    _plot_gappy(ax_x, times, pot_true, color=c_pot, linestyle="--", linewidth=1.3)
    _plot_gappy(ax_x, times, pot_pred, color=c_pot, linestyle="-", linewidth=1.5)
    _mark_horizon(ax_x, times, [(kin_pred, c_kin), (pot_pred, c_pot)], h)
    x_handles = [
        Line2D([], [], color=c_kin, linestyle="-", label="kinetic T predicted"),
        Line2D([], [], color=c_kin, linestyle="--", label="kinetic T true"),
        Line2D([], [], color=c_pot, linestyle="-", label="potential V predicted"),
        Line2D([], [], color=c_pot, linestyle="--", label="potential V true"),
    ]
    if has_h and (window is None or window[0] <= h <= window[1]):
        x_handles.append(_horizon_legend_handle())
    ax_x.set_xlabel("time t [s]")
    ax_x.set_ylabel("energy [J]")
    if window is None:
        ax_x.set_title("kinetic and potential energy")
    else:
        ax_x.set_title(f"kinetic and potential energy\n(window t = {_format_t(window[0])} … {_format_t(window[1])} s)")
    _legend_below(ax_x, x_handles, 2)

    for ax in (ax_q, ax_e, ax_x):
        ax.set_xlim(times[0], t_hi)
        ax.grid(alpha=0.3)
    if window is not None:
        margin = 0.02 * (window[1] - window[0])
        ax_x.set_xlim(window[0] - margin, window[1] + margin)
        inside = (times >= window[0]) & (times <= window[1])
        vals = np.concatenate([a[inside] for a in (kin_pred, pot_pred, kin_true, pot_true)])
        vals = vals[np.isfinite(vals)]
        if vals.size:  # the y range of what the window shows, not of the whole series
            lo, hi = float(vals.min()), float(vals.max())
            pad = 0.05 * (hi - lo) if hi > lo else max(abs(hi), 1.0) * 0.05
            ax_x.set_ylim(lo - pad, hi + pad)
    return ax_q, ax_e, ax_x


def _subscript(n: int) -> str:
    return str(n).translate(str.maketrans("0123456789", "₀₁₂₃₄₅₆₇₈₉"))


def _nonfinite_note(ax, n_bad: int, size: int) -> None:
    """The share of non-finite (grey) values, in a small box at the bottom of the panel."""
    if n_bad:
        ax.text(0.5, 0.03, f"non-finite\n{100.0 * n_bad / size:.0f}% (grey)",
                transform=ax.transAxes, ha="center", va="bottom", fontsize="x-small",
                bbox=dict(boxstyle="round", facecolor="white", alpha=0.8, linewidth=0))


def _snapshot_colorbars(fig, axes: np.ndarray, im_f, im_e, field_label: str, f_extend: str, e_extend: str) -> None:
    fig.colorbar(im_f, ax=axes[:2, :].ravel().tolist(), label=field_label, shrink=0.9, extend=f_extend)
    fig.colorbar(im_e, ax=axes[2, :].ravel().tolist(), label=_ERROR_LABEL, shrink=1.0, extend=e_extend)


def _label_snapshot_panels(axes: np.ndarray, times_shown: np.ndarray, h: float) -> None:
    row_names = ("predicted", "true", "|pred − true|")
    S = axes.shape[1]
    for s in range(S):
        for r in range(3):
            ax = axes[r, s]
            ax.tick_params(labelsize="small")
            if s == 0:
                ax.set_ylabel(f"{row_names[r]}\n{_X_LABELS[1]}")
            if r == 2:
                ax.set_xlabel(_X_LABELS[0])
        t = float(times_shown[s])
        where = "before horizon" if t < h else "after horizon"
        axes[0, s].set_title(f"t = {_format_t(t)} s\n({where})", fontsize="medium")


def _draw_fields(
    fig: Figure | SubFigure,
    grid_shape: tuple[int, int],
    extent: tuple[float, float, float, float],
    times_shown: np.ndarray,
    pred: np.ndarray,
    true: np.ndarray,
    h: float,
    field_label: str = "field q",
):
    import matplotlib as mpl

    S = pred.shape[0]
    err = np.abs(pred - true)  # NaN where pred is NaN
    vmax, f_extend = _field_scale(pred, true)
    emax, e_extend = _error_scale(err)

    cmap_f = mpl.colormaps[_FIELD_CMAP].with_extremes(bad=_MASK_COLOR)
    cmap_e = mpl.colormaps[_ERROR_CMAP].with_extremes(bad=_MASK_COLOR)

    axes = np.asarray(fig.subplots(3, S, sharex=True, sharey=True, squeeze=False))
    im_f = im_e = None
    for s in range(S):
        imgs = (pred[s], true[s], err[s])
        for r in range(3):
            ax = axes[r, s]
            img = np.ma.masked_invalid(imgs[r].reshape(grid_shape).T)
            if r < 2:
                im = ax.imshow(img, origin="lower", extent=extent, cmap=cmap_f, vmin=-vmax, vmax=vmax,
                               interpolation="nearest", aspect="equal")
                im_f = im
            else:
                im = ax.imshow(img, origin="lower", extent=extent, cmap=cmap_e, vmin=0.0, vmax=emax,
                               interpolation="nearest", aspect="equal")
                im_e = im
            _nonfinite_note(ax, int(np.count_nonzero(np.ma.getmaskarray(img))), img.size)
    _label_snapshot_panels(axes, times_shown, h)
    _snapshot_colorbars(fig, axes, im_f, im_e, field_label, f_extend, e_extend)
    return axes


#: A Delaunay triangle whose longest edge exceeds this many times the median edge of the triangulation is masked (not
#: drawn): it bridges a cut-out or notch of the body (an L-shape) that the convex hull would fill. Interior triangles
#: of uniformly random points stay below ~3.2 times the median edge.
_LONG_EDGE = 4.0


def _body_mask(xy: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(M,) True for the triangles that are not inside the body: those with an edge longer than :data:`_LONG_EDGE`
    times the median edge, which span a gap in the points (a concave corner, a hole) rather than the body."""
    corners = xy[triangles]  # (M, 3, 2)
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=-1)  # (M, 3)
    longest = edges.max(axis=1)
    mask = longest > _LONG_EDGE * float(np.median(edges))
    return np.zeros_like(mask) if mask.all() else mask


def _triangulate(xy: np.ndarray, what: str):
    """Delaunay triangulation of (N, 2) points, with the triangles that bridge gaps of the body masked (see
    :func:`_body_mask`), or a ValueError saying why there is none."""
    from matplotlib.tri import Triangulation

    if xy.shape[0] < 3:
        raise ValueError(f"{what}: need at least 3 points to triangulate, got {xy.shape[0]}")
    try:
        tri = Triangulation(xy[:, 0], xy[:, 1])
    except (ValueError, RuntimeError) as exc:
        raise ValueError(f"{what}: the {xy.shape[0]} points cannot be triangulated "
                         f"(all on one line, or too few distinct points): {exc}") from exc
    if tri.triangles.shape[0] == 0:
        raise ValueError(f"{what}: the {xy.shape[0]} points cannot be triangulated (all on one line)")
    mask = _body_mask(xy, tri.triangles)
    if mask.any():
        tri.set_mask(mask)
    return tri


def _draw_fields_scattered(
    fig: Figure | SubFigure,
    xy: np.ndarray,
    box: np.ndarray,
    times_shown: np.ndarray,
    pred: np.ndarray,
    true: np.ndarray,
    h: float,
    field_label: str = "field q",
    what: str = "points",
):
    """As :func:`_draw_fields` for fields on scattered points ``xy`` (N, 2): the same 3 × S panels (predicted,
    true, |pred − true|) drawn with ``tripcolor`` on the points' Delaunay triangulation, one colour per
    triangle (the mean of its vertices). Triangles that bridge a gap of the points (the cut-out of an L-shape,
    a hole: an edge over 4 times the median edge) are not drawn. A triangle touching a non-finite vertex is
    masked: drawn grey, and the panel notes the share of non-finite points. ``box`` (2, 2): the axis limits."""
    import matplotlib as mpl

    tri = _triangulate(xy, what)
    S = pred.shape[0]
    pred = np.where(np.isfinite(pred), pred, np.nan)
    true = np.where(np.isfinite(true), true, np.nan)
    err = np.abs(pred - true)  # NaN where pred or true is non-finite
    vmax, f_extend = _field_scale(pred, true)
    emax, e_extend = _error_scale(err)

    cmap_f = mpl.colormaps[_FIELD_CMAP].with_extremes(bad=_MASK_COLOR)
    cmap_e = mpl.colormaps[_ERROR_CMAP].with_extremes(bad=_MASK_COLOR)

    axes = np.asarray(fig.subplots(3, S, sharex=True, sharey=True, squeeze=False))
    im_f = im_e = None
    for s in range(S):
        vals = (pred[s], true[s], err[s])
        for r in range(3):
            ax = axes[r, s]
            v = vals[r]
            # per-triangle colour; NaN (a masked triangle, drawn in the colour map's grey "bad" colour)
            # wherever a vertex is non-finite
            face = v[tri.triangles].mean(axis=1)
            if r < 2:
                im = ax.tripcolor(tri, facecolors=face, cmap=cmap_f, vmin=-vmax, vmax=vmax, shading="flat")
                im_f = im
            else:
                im = ax.tripcolor(tri, facecolors=face, cmap=cmap_e, vmin=0.0, vmax=emax, shading="flat")
                im_e = im
            _nonfinite_note(ax, int(np.count_nonzero(~np.isfinite(v))), v.size)
            ax.set_xlim(box[0, 0], box[0, 1])
            ax.set_ylim(box[1, 0], box[1, 1])
            ax.set_aspect("equal")
    _label_snapshot_panels(axes, times_shown, h)
    _snapshot_colorbars(fig, axes, im_f, im_e, field_label, f_extend, e_extend)
    return axes


def _middle_slab(pts: np.ndarray, zlim: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Indices (sorted) of the points in the slab around the middle of the third axis: those within 1/16 of the
    z range of the middle (a slab 1/8 of the range thick), and never fewer than the nearest ⌈N/8⌉ (at least 3)
    points, ties included. Returns (indices, z middle, half thickness actually used)."""
    n = pts.shape[0]
    if n < 3:
        raise ValueError(f"points: a 3-D body needs at least 3 points for its middle slab, got {n}")
    z_mid = 0.5 * float(zlim[0] + zlim[1])
    half = (float(zlim[1]) - float(zlim[0])) / 16.0
    dz = np.abs(pts[:, 2] - z_mid)
    order = np.argsort(dz, kind="stable")
    k = max(int(np.count_nonzero(dz <= half)), min(n, max(3, -(-n // 8))))
    # points as near as the k-th come too (a layered mesh gives whole layers, never a part of one)
    tol = 1e-9 * (float(zlim[1]) - float(zlim[0]))
    sel = np.flatnonzero(dz <= dz[order[k - 1]] + tol)
    return sel, z_mid, max(half, float(dz[sel].max()))


def _cell_edges(c: np.ndarray, lo: float | None = None, hi: float | None = None) -> np.ndarray:
    """Cell edges of sorted (non-decreasing) centres ``c``: midpoints between neighbours, the outer edges half
    a neighbour gap beyond the end centres, pulled in to ``lo`` / ``hi`` where the end centre lies inside them
    (a midpoint grid gets back exactly its box). One centre gets [lo, hi], or c ± ½ without them."""
    c = np.asarray(c, dtype=float)
    if c.shape[0] == 1:
        a = lo if lo is not None and lo < c[0] else c[0] - 0.5
        b = hi if hi is not None and hi > c[0] else c[0] + 0.5
        return np.array([a, b])
    mid = 0.5 * (c[1:] + c[:-1])
    first = c[0] - 0.5 * (c[1] - c[0])
    last = c[-1] + 0.5 * (c[-1] - c[-2])
    if lo is not None and c[0] >= lo:
        first = max(first, lo)
    if hi is not None and c[-1] <= hi:
        last = min(last, hi)
    return np.concatenate([[first], mid, [last]])


def _draw_fields_1d(fig: Figure | SubFigure, x: np.ndarray, t: np.ndarray, pred: np.ndarray, true: np.ndarray,
                    idx: list[int], h: float, field_label: str = "field q", x_edges: np.ndarray | None = None):
    """A 1-D body: space–time images of predicted, true and |pred − true| (x across, t up, the training
    horizon dashed), and below them the fields at the snapshot times, predicted solid, true dotted.

    x: the (sorted) points. Without ``x_edges`` x is a uniform midpoint grid drawn with imshow; with them
    (len(x) + 1 cell edges, possibly non-uniform) the images are a pcolormesh over those x cells and time cells
    between neighbouring samples, so non-uniform spacing is drawn as it is."""
    import matplotlib as mpl

    err = np.abs(pred - true)
    vmax, f_extend = _field_scale(pred, true)
    emax, e_extend = _error_scale(err)
    top, bottom = fig.subfigures(2, 1, height_ratios=[1.3, 1.0])
    axes = np.asarray(top.subplots(1, 3, sharex=True, sharey=True, squeeze=False))[0]
    dx = float(x[1] - x[0]) if len(x) > 1 else 1.0
    extent = (float(x[0] - dx / 2), float(x[-1] + dx / 2), float(t[0]), float(t[-1]))
    if x_edges is not None:
        t_edges = _cell_edges(t, float(t[0]), float(t[-1]))
    for ax, img, name, cmap, lo, hi, label, extend in (
            (axes[0], pred, "predicted", _FIELD_CMAP, -vmax, vmax, field_label, f_extend),
            (axes[1], true, "true", _FIELD_CMAP, -vmax, vmax, field_label, "neither"),
            (axes[2], err, "|pred − true|", _ERROR_CMAP, 0.0, emax, _ERROR_LABEL, e_extend)):
        cm = mpl.colormaps[cmap].with_extremes(bad=_MASK_COLOR)
        if x_edges is None:
            im = ax.imshow(np.ma.masked_invalid(img), origin="lower", extent=extent, aspect="auto", vmin=lo,
                           vmax=hi, cmap=cm, interpolation="nearest")
        else:
            im = ax.pcolormesh(x_edges, t_edges, np.ma.masked_invalid(img), shading="flat", vmin=lo, vmax=hi,
                               cmap=cm)
            ax.set_xlim(x_edges[0], x_edges[-1])
            ax.set_ylim(t_edges[0], t_edges[-1])
        ax.axhline(h, color="k", ls="--", lw=0.9)
        ax.set_title(name)
        ax.set_xlabel(_X_LABELS[0])
        ax.tick_params(labelsize="small")
        top.colorbar(im, ax=ax, label=label, shrink=0.9, extend=extend)
    axes[0].set_ylabel("time t [s]\n(dashed: training horizon)")
    ax = bottom.subplots()
    colors = mpl.colormaps["viridis"](np.linspace(0, 0.9, len(idx)))
    for c, i in zip(colors, idx):
        where = "before" if t[i] < h else "after"
        ax.plot(x, pred[i], color=c, lw=1.6, label=f"t = {_format_t(float(t[i]))} s ({where} horizon)")
        ax.plot(x, true[i], color=c, lw=1.6, ls=":")
    ax.set_xlabel(_X_LABELS[0])
    ax.set_ylabel(f"{field_label}\n(solid: predicted, dotted: true)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return axes


def _draw_scattered_body(fig: Figure | SubFigure, pts: np.ndarray, box: np.ndarray, t: np.ndarray,
                         pf: np.ndarray, tf: np.ndarray, idx: list[int], h: float, field_label: str) -> None:
    """The field panels of :func:`figure3` for fields (T, N) on scattered points (N, dim_B)."""
    dim = pts.shape[1]
    if dim == 1:
        order = np.argsort(pts[:, 0], kind="stable")
        x = pts[order, 0]
        _draw_fields_1d(fig, x, t, pf[:, order], tf[:, order], idx, h, field_label,
                        x_edges=_cell_edges(x, float(box[0, 0]), float(box[0, 1])))
        return
    what = "points"
    if dim == 3:
        sel, z_mid, half = _middle_slab(pts, box[2])
        pts, pf, tf = pts[sel], pf[:, sel], tf[:, sel]
        field_label = f"{field_label}\n(slab {_X_LABELS[2]} ≈ {z_mid:.3g} ± {half:.2g}, {sel.shape[0]} points)"  # two lines: clear of the error bar's label
        what = f"points of the slab {_X_LABELS[2]} ≈ {z_mid:.3g} ± {half:.2g}"
    _draw_fields_scattered(fig, pts[:, :2], box[:2], t[idx], pf[idx], tf[idx], h, field_label, what)


# --------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------


def latent_and_energy_figure(
    times,
    q_pred,
    q_proj,
    kinetic_pred,
    potential_pred,
    kinetic_true,
    potential_true,
    train_horizon: float,
    title: str = "",
) -> Figure:
    """Figure 3, top row: latent q̃(t) predicted (solid) vs projected (dashed); the total energy predicted
    (solid) vs true (dashed) over the whole range; the kinetic and potential energies predicted (solid) vs true
    (dashed), over the whole range, or where they oscillate more than 8 times in a window of 4 periods around
    the training horizon (shaded on the total-energy panel). The training horizon is marked (● and a dotted line).

    times: (T,) seconds, strictly increasing. q_pred, q_proj: (T, d) (a (T,) array means d = 1).
    Energies: (T,) each, in joules.
    """
    t = _check_times(times)
    T = t.shape[0]
    qp = _check_latent(q_pred, "q_pred", T)
    qr = _check_latent(q_proj, "q_proj", T, qp.shape[1])
    kp = _check_series(kinetic_pred, "kinetic_pred", T)
    pp = _check_series(potential_pred, "potential_pred", T)
    kt = _check_series(kinetic_true, "kinetic_true", T)
    pt = _check_series(potential_true, "potential_true", T)
    h = _check_scalar(train_horizon, "train_horizon")

    fig = Figure(figsize=(13.0, 4.4), layout="constrained")
    _roomy(fig)
    _draw_latent_energy(fig, t, qp, qr, kp, pp, kt, pt, h)
    if title:
        fig.suptitle(title)
    return fig


def field_snapshots_figure(
    grid_shape: tuple[int, int],
    bounds,
    times_shown: Sequence[float],
    pred: np.ndarray,
    true: np.ndarray,
    train_horizon: float,
    title: str = "",
) -> Figure:
    """Figure 3, bottom: one column per shown time with the predicted field, the true field and
    |pred − true|. pred, true: (S, Nf) with S = len(times_shown), Nf = nx·ny, each row a field on a
    row-major ('ij': first axis is x) grid of ``grid_shape = (nx, ny)``. ``bounds`` is
    ((xmin, xmax), (ymin, ymax)) or (xmin, xmax, ymin, ymax).
    """
    gs = _check_grid_shape(grid_shape)
    extent = _check_bounds(bounds)
    ts = _check_times(times_shown, "times_shown", increasing=False)
    S = ts.shape[0]
    nf = gs[0] * gs[1]
    p = _check_fields(pred, "pred", S, nf, "S")
    q = _check_fields(true, "true", S, nf, "S")
    h = _check_scalar(train_horizon, "train_horizon")

    fig = Figure(figsize=(2.4 * S + 2.2, 7.5), layout="constrained")
    _roomy(fig)
    _draw_fields(fig, gs, extent, ts, p, q, h)
    if title:
        fig.suptitle(title)
    return fig


def default_snapshot_indices(times, train_horizon: float, n_each: int = 2) -> list[int]:
    """``n_each`` evenly spaced sample indices in each of [before horizon) and [after horizon].

    Samples with t < train_horizon form the first half, the rest the second; in each half of n
    samples, index start + floor((i + ½)·n / n_each) for i = 0..n_each−1 (for n_each = 2: the one-
    and three-quarter points). For 100 samples at 0.05 s and horizon 2.5 s this gives [12, 37, 62, 87].
    A half with no samples contributes nothing; duplicates (n_each > n) are dropped.
    """
    t = _check_times(times)
    h = _check_scalar(train_horizon, "train_horizon")
    if int(n_each) != n_each or n_each < 1:
        raise ValueError(f"n_each must be a positive int, got {n_each!r}")
    n_each = int(n_each)
    split = int(np.searchsorted(t, h, side="left"))  # first index with t >= h
    out: list[int] = []
    for start, stop in ((0, split), (split, t.shape[0])):
        n = stop - start
        if n <= 0:
            continue
        for i in range(n_each):
            k = start + int(np.floor((i + 0.5) * n / n_each))
            k = min(k, stop - 1)
            if not out or out[-1] != k:
                out.append(k)
    return out


def figure3(
    times,
    q_pred,
    q_proj,
    energies: Mapping[str, np.ndarray],
    grid_shape,
    bounds,
    pred_fields,
    true_fields,
    snapshot_indices: Sequence[int] | None,
    train_horizon: float,
    title: str = "",
    field_label: str = "field q",
    *,
    points=None,
) -> Figure:
    """The paper's Figure 3 in one figure: top row latent and energies, below the fields.

    The fields are given either on a grid or on scattered points:

    - ``grid_shape``: points per axis (1 to 3 ints, row-major, first axis x) of a midpoint grid on the box
      ``bounds`` ([[lo, hi], ...] of those axes); pred_fields, true_fields: (T, Nf) with Nf = prod(grid_shape).
      A 1-D body is drawn as space–time images (predicted, true, error) and line plots at the snapshot times,
      a 2-D body as images at the snapshot times, a 3-D body as the images of its middle slice across the
      third axis.
    - ``grid_shape=None`` and ``points`` (N, dim_B) (mesh nodes, random samples, in any order): pred_fields,
      true_fields: (T, N) on those points; bounds: [[lo, hi], ...] of the dim_B axes. A 1-D body is drawn as
      above with the points sorted by x, each one's cell reaching halfway to its neighbours (non-uniform
      spacing shown as it is); a 2-D body as the same panels drawn on the points' Delaunay triangulation
      (triangles touching a non-finite value grey; triangles with an edge over 4 times the median edge, which
      bridge a cut-out or hole of the body, left out), the box as axis limits; a 3-D body as the 2-D drawing of
      the points in a slab around the middle of the third axis (1/8 of its range thick, widened to the
      nearest ⌈N/8⌉ points if it holds fewer; at least 3 points needed).

    When both are given, ``grid_shape`` is used and ``points`` is ignored.

    energies: mapping with keys ``ENERGY_KEYS`` ("kinetic_pred", "potential_pred", "kinetic_true",
    "potential_true"), each (T,). snapshot_indices: indices into the T samples
    (None -> :func:`default_snapshot_indices`).
    """
    t = _check_times(times)
    T = t.shape[0]
    qp = _check_latent(q_pred, "q_pred", T)
    qr = _check_latent(q_proj, "q_proj", T, qp.shape[1])
    if not isinstance(energies, Mapping):
        raise ValueError(f"energies must be a mapping with keys {ENERGY_KEYS}, got {type(energies).__name__}")
    missing = [k for k in ENERGY_KEYS if k not in energies]
    if missing:
        raise ValueError(f"energies is missing keys {missing}; expected keys {ENERGY_KEYS}")
    e = {k: _check_series(energies[k], f"energies[{k!r}]", T) for k in ENERGY_KEYS}
    if grid_shape is not None:
        gs = _check_grid_shape_nd(grid_shape)
        pts = None
        dim = len(gs)
        box = _check_box(bounds, dim)
        nf, nf_label = int(np.prod(gs)), "Nf = prod(grid_shape)"
    elif points is None:
        raise ValueError("figure3 needs grid_shape (points per axis of a grid) or points (an (N, dim_B) array "
                         "of the evaluation points); both are None")
    else:
        pts = _check_points(points)
        gs = None
        dim = pts.shape[1]
        box = _check_box(bounds, dim, f"the points (shape {pts.shape})")
        nf, nf_label = pts.shape[0], "N = len(points)"
    pf = _check_fields(pred_fields, "pred_fields", T, nf, "T", nf_label)
    tf = _check_fields(true_fields, "true_fields", T, nf, "T", nf_label)
    h = _check_scalar(train_horizon, "train_horizon")

    if snapshot_indices is None:
        idx = default_snapshot_indices(t, h)
    else:
        try:
            idx = [int(i) for i in snapshot_indices]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"snapshot_indices must be a sequence of ints, got {snapshot_indices!r}") from exc
        if any(int(i) != i for i in snapshot_indices):
            raise ValueError(f"snapshot_indices must be ints, got {list(snapshot_indices)!r}")
    if not idx:
        raise ValueError("snapshot_indices must contain at least one index")
    bad = [i for i in idx if not (-T <= i < T)]
    if bad:
        raise ValueError(f"snapshot_indices must lie in [0, T) with T = len(times) = {T}, got {bad}")
    idx = [i % T for i in idx]
    S = len(idx)

    width = max(13.0, 2.4 * S + 2.2)
    snapshots = (pts is not None and pts.shape[1] >= 2) or (pts is None and len(gs) >= 2)  # 2-D panels
    top_h = 4.4
    if snapshots:  # three rows of panels of the box's aspect: as tall as they need, no taller
        panel_w, panel_h = _panel_size(width, S, box)
        bottom_h = 3.0 * (panel_h + 0.55) + 0.5
    else:
        bottom_h = 8.2
    fig = Figure(figsize=(width, top_h + bottom_h), layout="constrained")
    _roomy(fig)
    top, bottom = fig.subfigures(2, 1, height_ratios=[top_h, bottom_h])
    _draw_latent_energy(top, t, qp, qr, e["kinetic_pred"], e["potential_pred"],
                        e["kinetic_true"], e["potential_true"], h)
    if snapshots:
        bottom = _centred(bottom, width, S, panel_w)
    if pts is not None:
        _draw_scattered_body(bottom, pts, box, t, pf, tf, idx, h, field_label)
    elif len(gs) == 1:
        _draw_fields_1d(bottom, np.linspace(*box[0], gs[0] + 1)[:-1] + 0.5 * (box[0, 1] - box[0, 0]) / gs[0],
                        t, pf, tf, idx, h, field_label)
    else:
        if len(gs) == 3:  # the middle slice across the third axis (a midpoint grid's cell centres)
            k = gs[2] // 2
            z = box[2, 0] + (k + 0.5) * (box[2, 1] - box[2, 0]) / gs[2]
            pf, tf = (f.reshape(T, *gs)[..., k].reshape(T, -1) for f in (pf, tf))
            field_label = f"{field_label} (slice {_X_LABELS[2]} = {z:.3g})"
        _draw_fields(bottom, gs[:2], tuple(box[:2].reshape(-1)), t[idx], pf[idx], tf[idx], h, field_label)
    if title:
        fig.suptitle(title)
    return fig


def vector_path(path) -> Path:
    """Where :func:`save_figure` writes the PDF of a PNG at ``path``: the same stem with suffix ``.pdf``
    (``fig3.png`` → ``fig3.pdf``); for a ``path`` that itself ends in ``.pdf`` (the PNG then has that name),
    ``<stem>.vector.pdf``."""
    path = Path(path)
    pdf = path.with_suffix(".pdf")
    return pdf if pdf != path else path.with_name(f"{path.stem}.vector.pdf")


def _roomy(fig: Figure) -> None:
    """More room between panels (and at the edges, where a tick label at the end of an axis reaches out) than
    constrained layout's default."""
    fig.get_layout_engine().set(w_pad=0.1, h_pad=0.06, wspace=0.03, hspace=0.02)


_PANEL = 2.4  # inches: the side of a square snapshot panel of Figure 3
_PANEL_EXTRA = 2.6  # inches beside the snapshot columns: row labels, colour bars


def _panel_size(width: float, S: int, box: np.ndarray) -> tuple[float, float]:
    """(width, height) in inches of one snapshot panel of a 2-D box (its aspect kept) when S columns share a figure
    ``width`` inches wide: a square one ``_PANEL`` a side, a wide one as wide as fits (then less tall)."""
    aspect = float(box[0, 1] - box[0, 0]) / float(box[1, 1] - box[1, 0])
    w = min(_PANEL * max(aspect, 1.0), (width - _PANEL_EXTRA) / S)
    if aspect < 1.0:  # a tall body: ``_PANEL`` tall at most
        w = min(w, _PANEL * aspect)
    return w, w / aspect


def _centred(sub: SubFigure, width: float, S: int, panel_w: float) -> SubFigure:
    """The middle part of ``sub`` (a figure ``width`` inches wide) just wide enough for S columns of panels
    ``panel_w`` inches wide and their colour bars, so that a few snapshots do not spread over the whole width."""
    need = S * panel_w + _PANEL_EXTRA
    if need >= width - 0.5:
        return sub
    side = 0.5 * (width - need)
    return sub.subfigures(1, 3, width_ratios=[side, need, side])[1]


def save_figure(fig: Figure, path, *, pdf: bool | None = None, **savefig_kwargs) -> Path:
    """Write ``fig`` as a PNG (200 dpi) to ``path`` and, with ``pdf``, as a vector PDF of the same stem beside
    it (:func:`vector_path`: ``fig3.png`` → ``fig3.pdf``), both atomically; return the PNG's path. ``pdf=None``
    (the default) writes the PDF unless the environment sets ``LNF_FIGURE_PDF=0`` (PNG only: quicker, for
    runs that draw many figures nobody will print).

    Each file is rendered to a uniquely named temporary file in the same directory, then ``os.replace``d
    onto its name, so a reader never sees a half-written file (nor a temporary one after an error: they are
    removed). Parent directories are created. The raster is always PNG, whatever the suffix of ``path``. The
    PDF embeds its fonts as TrueType (editable text). Other keyword arguments (``dpi`` too) go to
    ``fig.savefig`` for both files.
    """
    import matplotlib as mpl

    if not isinstance(fig, Figure):
        raise ValueError(f"fig must be a matplotlib.figure.Figure, got {type(fig).__name__}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stamp = f"{os.getpid()}.{uuid.uuid4().hex[:8]}"
    if pdf is None:
        pdf = os.environ.get("LNF_FIGURE_PDF", "1").strip().lower() not in ("0", "false", "no", "off")
    targets = [(path, "png")] + ([(vector_path(path), "pdf")] if pdf else [])
    temps = [(target.with_name(f".{target.name}.{stamp}.tmp.{fmt}"), target, fmt) for target, fmt in targets]
    dpi = savefig_kwargs.pop("dpi", _DPI)  # of the PNG, and of the images embedded in the PDF
    try:
        for tmp, _, fmt in temps:
            with mpl.rc_context({"pdf.fonttype": 42}):
                fig.savefig(tmp, format=fmt, dpi=dpi, **savefig_kwargs)
        for tmp, target, _ in temps:
            os.replace(tmp, target)
    except BaseException:
        for tmp, _, _ in temps:
            try:
                tmp.unlink()
            except FileNotFoundError:
                pass
        raise
    return path
