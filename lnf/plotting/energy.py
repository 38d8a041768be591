"""The latent and energy panels of Figure 3: q̃(t) predicted against projected, energies, the training horizon."""
from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure, SubFigure

from lnf.plotting.style import _HORIZON_STYLE, _MAX_PERIODS, _WINDOW_PERIODS, _format_t, _subscript


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
