"""A study's charts: each method's style, metric keys in words, legends outside the data, labels that do not
overlap, PNG and vector PDF output."""
from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any, Iterable, Optional, Sequence

import numpy as np

#: each method's name in words, colour and marker (the methods of ``METHODS``, ours with the closure, and the two of
#: Operator Inference)
LABELS = {"lnf": "LNF (ours)", "lnf_closure": "LNF + closure (ours)", "latent_mlp": "black-box latent MLP",
          "pod": "POD-Galerkin", "full_order": "full order", "opinf": "Operator Inference (full states)",
          "opinf_observed": "Operator Inference (sparse observations)"}
COLORS = {"lnf": "tab:blue", "lnf_closure": "tab:cyan", "latent_mlp": "tab:red", "pod": "tab:green",
          "full_order": "tab:gray", "opinf": "tab:purple", "opinf_observed": "tab:pink"}
MARKERS = {"lnf": "o", "lnf_closure": "h", "latent_mlp": "s", "pod": "^", "full_order": "D", "opinf": "v",
           "opinf_observed": "<"}

#: what a metric measures, in words, and its unit ("" where it has none): the first part of a metric key
#: ``<quantity>/<subset>/<statistic>`` (docs/method.md §7.3), or a whole key without slashes
QUANTITY_WORDS: dict[str, tuple[str, str]] = {
    "field_rel_l2": ("relative L² field error", ""),
    "projection_rel_l2": ("relative L² error of the projected field", ""),
    "latent_rmse": ("latent RMSE", ""),
    "energy_rel_err": ("energy error max_t |Ẽ − E| / E_scale", ""),
    "energy_drift": ("energy drift max_t |Ẽ(t) − Ẽ(0)| / E_scale", ""),
    "energy_drift_long": ("energy drift max_t |Ẽ(t) − Ẽ(0)| / E_scale (long run)", ""),
    "vpt": ("valid prediction time", "s"),
    "rollout_seconds_per_trajectory": ("latent rollout wall-clock per trajectory", "s"),
    "rollout_seconds_per_step": ("latent rollout wall-clock per step", "s"),
    "decode_seconds_per_trajectory": ("decoding wall-clock per trajectory", "s"),
    "fields_seconds_per_trajectory": ("rollout + decoding wall-clock per trajectory", "s"),
    "cost_seconds": ("rollout + decoding wall-clock per trajectory", "s"),
    "train_seconds": ("training wall-clock", "s"),
    "evaluation_seconds": ("evaluation wall-clock", "s"),
    "rollout_seconds": ("rollout wall-clock", "s"),
    "decode_seconds": ("decoding wall-clock", "s"),
    "total_seconds": ("rollout + decoding wall-clock", "s"),
    "rollout_peak_mib": ("peak memory of the rollout above baseline", "MiB"),
    "decode_peak_mib": ("peak memory of the decoding above baseline", "MiB"),
    "peak_mib": ("peak memory above baseline", "MiB"),
    "points": ("evaluation points", ""),
    "batch": ("trajectories rolled out at once", ""),
    "flops": ("matmul FLOPs of one RK4 step", ""),
    "seconds": ("measured time of one RK4 step", "s"),
    "bound_seconds": ("FLOP bound of one RK4 step", "s"),
    "ratio": ("measured time / FLOP bound", ""),
    "gflops_achieved": ("achieved matmul throughput", "GFLOP/s"),
    "diverged_fraction": ("share of diverged test rollouts", ""),
    # sweep settings
    "model.width": ("SIREN width (neurons per hidden layer)", ""),
    "model.latent_dim": ("latent dimension d", ""),
    "model.depth": ("SIREN depth (hidden layers)", ""),
    "model.reduction_steps": ("reduction steps K", ""),
    "model.resolution": ("full-order grid points per axis", ""),
    "data.observed_fraction": ("observed share of the coarse training grid", ""),
    "data.noise": ("observation noise (std / RMS of the observed values)", ""),
    "dt": ("time step dt", "s"),
    "quadrature.order": ("Gauss–Legendre points per axis", ""),
    "quadrature.resolution": ("uniform quadrature points per axis", ""),
}
SUBSET_WORDS = {"all": "", "in_horizon": "within the training horizon", "extrapolation": "after the training horizon"}


def metric_label(key: str, split: str = "test", over: str = "trajectories", wrap: bool = False) -> str:
    """A metric key (``field_rel_l2/extrapolation/median``, ``train_seconds``, ``model.width``) in words with its
    unit, as an axis label: "relative L² field error after the training horizon (test, median over
    trajectories)", "training wall-clock [s]". `split` names the trajectories a ``<quantity>/<subset>/<stat>``
    metric is taken on, `over` what its statistic runs over; `wrap` breaks the line before the parenthesis. A key
    the table does not know is returned as it is."""
    parts = key.split("/")
    words, unit = QUANTITY_WORDS.get(parts[0], (None, ""))
    if words is None:
        return key
    subset = SUBSET_WORDS.get(parts[1], parts[1]) if len(parts) == 3 else ""
    stat = parts[-1] if len(parts) >= 2 else ""
    text = words + (f" {subset}" if subset else "")
    detail = ", ".join(p for p in (split if len(parts) >= 2 else "", f"{stat} over {over}" if stat else "") if p)
    units = f" [{unit}]" if unit else ""
    if detail:
        return f"{text}{units}" + ("\n" if wrap else " ") + f"({detail})"
    return f"{text}{units}"


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (no display needed), imported when a study draws its first chart."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: Path) -> Path:
    """The figure as a PNG (200 dpi) and a vector PDF of the same stem beside it (``pareto.png`` and
    ``pareto.pdf``), each written atomically by :func:`lnf.plotting.save_figure` and cropped to its content;
    returns the PNG's path and closes the figure."""
    import matplotlib.pyplot as plt

    from lnf.plotting import save_figure as save_png_and_pdf

    try:
        return save_png_and_pdf(fig, path, bbox_inches="tight")
    finally:
        plt.close(fig)


#: line styles that keep coincident curves apart (with the method's marker and colour)
LINESTYLES = {"lnf": "-", "latent_mlp": "--", "pod": "-.", "full_order": ":", "opinf": (0, (3, 1, 1, 1, 1, 1)),
              "opinf_observed": (0, (1, 1))}
#: where each method's curve sits in a small sideways dodge (steps of DODGE_FRACTION of the x range)
DODGE = {"lnf": -1.5, "latent_mlp": -0.5, "pod": 0.5, "full_order": 1.5, "opinf": 2.5, "opinf_observed": 3.5}
DODGE_FRACTION = 0.012
DODGE_NOTE = "curves drawn slightly apart in x (a few % of the axis at most) so that equal values stay visible"


def dodged(x: Any, method: str, log: bool = True, steps: Optional[float] = None) -> np.ndarray:
    """x moved sideways by `steps` (default ``DODGE[method]``) × DODGE_FRACTION of its range (in decades on a log
    axis, at least half a decade; linear: of its span), so that curves of several methods with equal values stay
    visible side by side. Ticks stay at the true values (:func:`ticks_at`)."""
    x = np.asarray(x, dtype=float)
    c = DODGE.get(method, 0.0) if steps is None else float(steps)
    fin = x[np.isfinite(x) & (x > 0)] if log else x[np.isfinite(x)]
    if log:
        span = max(float(np.log10(fin.max() / fin.min())), 0.5) if fin.size else 0.5
        return x * 10.0 ** (c * DODGE_FRACTION * span)
    span = float(np.ptp(fin)) if fin.size > 1 else 0.0
    return x + c * DODGE_FRACTION * (span if span > 0 else max(float(np.abs(fin).max()) if fin.size else 1.0, 1e-12))


def plot_marking_failures(ax: Any, x: np.ndarray, y: np.ndarray, failed: np.ndarray, *fmt: str, **kwargs: Any) -> None:
    """Line of y against x where non-finite or `failed` points are drawn at 10 and marked × (in the line's
    colour, black edge). The line is slightly transparent (alpha 0.85 unless given) and its markers are hollow-
    edged, so that a curve on top of another leaves it visible."""
    failed = np.asarray(failed, bool) | ~np.isfinite(y)
    yy = np.where(np.isfinite(y), y, 10.0)
    kwargs.setdefault("alpha", 0.85)
    kwargs.setdefault("markersize", 6)
    kwargs.setdefault("markeredgecolor", "white")
    kwargs.setdefault("markeredgewidth", 0.6)
    (line,) = ax.plot(x, yy, *fmt, **kwargs)
    if failed.any():
        ax.scatter(x[failed], yy[failed], marker="X", s=70, color=line.get_color(), edgecolors="k", linewidths=0.6,
                   zorder=4)


def legend_outside(ax: Any, where: str = "right", fontsize: float | str = "small", **kwargs: Any) -> Any:
    """The legend of `ax` outside its data: to the right of the axes (``where="right"``) or under its x label
    (``"below"``, several columns; set the x label first: the legend starts as far below the axes as the tick
    labels and the label's lines reach). Constrained layout (or ``bbox_inches="tight"``) makes room for it."""
    if where == "below":
        import matplotlib as mpl
        from matplotlib.font_manager import FontProperties
        from matplotlib.transforms import offset_copy

        rc = mpl.rcParams
        size = lambda key: FontProperties(size=rc[key]).get_size_in_points()  # noqa: E731
        label = ax.get_xlabel()
        lines = label.count("\n") + 1 if label else 0
        drop = (rc["xtick.major.size"] + rc["xtick.major.pad"] + 1.3 * size("xtick.labelsize")
                + (rc["axes.labelpad"] + 1.25 * size("axes.labelsize") * lines if lines else 0) + 3.0)
        below = offset_copy(ax.transAxes, fig=ax.figure, x=0.0, y=-drop, units="points")
        kwargs.setdefault("ncols", 2)
        return ax.legend(loc="upper center", bbox_to_anchor=(0.5, 0.0), bbox_transform=below, fontsize=fontsize,
                         frameon=False, borderaxespad=0.0, **kwargs)
    return ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, fontsize=fontsize,
                     frameon=False, **kwargs)


def figure_legend(fig: Any, axes: Sequence[Any], ncols: int = 4, fontsize: float | str = "small", **kwargs: Any) -> Any:
    """One legend for all `axes` (entries with the same label once), below the panels, outside the data (the
    figure must use constrained layout)."""
    handles: dict[str, Any] = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if not lab.startswith("_"):
                handles.setdefault(lab, h)
    if not handles:
        return None
    return fig.legend(list(handles.values()), list(handles), loc="outside lower center", fontsize=fontsize,
                      ncols=min(ncols, len(handles)), frameon=False, **kwargs)


def readable_log_ticks(ax: Any, decades: float = 2.5) -> None:
    """Tick labels of the log axes of `ax` that do not run into each other: no minor tick labels (matplotlib labels
    2×10⁻¹, 3×10⁻¹, … on a short log axis, which collide on a narrow panel); an axis spanning fewer than `decades`
    decades gets its major ticks at 1, 2 and 5 × 10^k, written plainly ("0.2", "5"). Call it once the data are
    drawn (it reads the limits); an axis with ticks of its own (:func:`ticks_at`) is left as it is."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, LogFormatterSciNotation, LogLocator, NullFormatter

    for name in ("x", "y"):
        axis = getattr(ax, f"{name}axis")
        if axis.get_scale() != "log" or isinstance(axis.get_major_locator(), FixedLocator):
            continue
        base = getattr(axis.get_transform(), "base", 10.0)
        lo, hi = sorted(getattr(ax, f"get_{name}lim")())
        if base == 10 and lo > 0 and np.log10(hi / lo) < decades:
            axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        else:  # (again: a shared axis may have been narrower at an earlier call)
            axis.set_major_locator(LogLocator(base=base))
            axis.set_major_formatter(LogFormatterSciNotation(base=base))
        axis.set_minor_formatter(NullFormatter())


def log_axes(ax: Any, legend_size: float | str = "small", x_base: float = 10, legend: str = "right") -> None:
    """Log–log axes with a light grid, readable tick labels (:func:`readable_log_ticks`; call it after drawing the
    data) and a legend outside the data (`legend`: "right", "below", or "none")."""
    ax.set_xscale("log", base=x_base)
    ax.set_yscale("log")
    ax.grid(True, which="major", alpha=0.35)
    ax.grid(True, which="minor", alpha=0.12)
    readable_log_ticks(ax)
    if legend != "none":
        legend_outside(ax, legend, fontsize=legend_size)


def _line_samples(ax: Any, step_px: float) -> np.ndarray:
    """Points every `step_px` pixels along the lines of `ax` (steps drawn as steps, axvlines included), (n, 2)
    in display coordinates: labels must not sit on them."""
    from matplotlib import cbook

    out = [np.zeros((0, 2))]
    for line in ax.get_lines():
        xy = np.asarray(line.get_xydata(), dtype=float)
        if len(xy) == 0 or line.get_linestyle() in ("None", "none", "", " "):
            continue
        style = line.get_drawstyle()
        if style and style.startswith("steps") and len(xy) > 1:
            xy = np.column_stack(cbook.STEP_LOOKUP_MAP[style](xy[:, 0], xy[:, 1]))
        with np.errstate(all="ignore"):
            d = line.get_transform().transform(xy)
        d = d[np.all(np.isfinite(d), axis=1)]
        for p, q in zip(d[:-1], d[1:]):
            n = max(2, int(np.hypot(*(q - p)) / step_px) + 1)
            out.append(p + np.linspace(0.0, 1.0, n)[:, None] * (q - p))
    return np.concatenate(out)


def ticks_at(ax: Any, values: Iterable[Any], axis: str = "x", fmt: Any = None) -> None:
    """Major ticks of `axis` at the (positive, finite) `values` a sweep took, labelled plainly ("0.05", "64";
    `fmt(value)` for another text), no minor tick labels: a log axis of a few settings reads as those settings,
    not as 2×10⁻¹, 3×10⁻¹ ... labels that run into each other."""
    from matplotlib.ticker import NullFormatter

    vals = []
    for v in values:
        try:
            v = float(v)
        except (TypeError, ValueError):
            continue
        if np.isfinite(v) and v > 0 and v not in vals:
            vals.append(v)
    if not vals:
        return
    vals.sort()
    getattr(ax, f"set_{axis}ticks")(vals, [fmt(v) if fmt else f"{v:g}" for v in vals])
    getattr(ax, f"{axis}axis").set_minor_formatter(NullFormatter())


def place_labels(ax: Any, xs: Sequence[float], ys: Sequence[float], texts: Sequence[str], fontsize: float = 7,
                 avoid: Sequence[tuple[float, float]] = (), pad_points: float = 2.5) -> list[Any]:
    """Annotate the points (xs[i], ys[i]) (data coordinates) with texts[i], each placed greedily at the first of
    a ring of offsets around its point (near first, then farther, with a thin leader line) whose box overlaps
    neither a label placed before, nor a marker (the points themselves and `avoid`), nor a line of the axes, nor
    its edge. A label that fits nowhere is left out. Measured with the figure's renderer after its layout is
    done: call it once the axes' limits, scales and the figure's legends are final (the labels themselves are
    kept out of the layout). Returns the annotations drawn."""
    from lnf.plotting import _DPI

    fig = ax.figure
    dpi = fig.dpi
    fig.set_dpi(_DPI)  # measured at the PNG's resolution: text widths vary a little with the dpi (hinting)
    try:
        return _place_labels(ax, xs, ys, texts, fontsize, avoid, pad_points)
    finally:
        fig.set_dpi(dpi)


def _place_labels(ax: Any, xs: Sequence[float], ys: Sequence[float], texts: Sequence[str], fontsize: float,
                  avoid: Sequence[tuple[float, float]], pad_points: float) -> list[Any]:
    fig = ax.figure
    fig.draw_without_rendering()  # the final layout and limits: positions below are those of the saved figure
    renderer = fig.canvas.get_renderer()
    to_px = fig.dpi / 72.0
    frame = ax.get_window_extent(renderer)
    marker_pt = 4.5  # half a marker's size [points]
    r = marker_pt * to_px
    with np.errstate(all="ignore"):  # a point a log axis cannot show is no obstacle
        pts = np.array([ax.transData.transform((float(x), float(y))) for x, y in list(zip(xs, ys)) + list(avoid)]
                       ).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    lines = _line_samples(ax, 2.0 * to_px)
    lw = 1.0 * to_px
    boxes = np.concatenate([np.column_stack([pts - r, pts + r]), np.column_stack([lines - lw, lines + lw])])
    out = []
    rings = [(1.0, False), (1.8, True), (2.8, True)]
    dirs = [(1, 1), (1, -1), (-1, 1), (-1, -1), (1, 0), (-1, 0), (0, 1), (0, -1)]
    for x, y, text in zip(xs, ys, texts):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        for (scale, leader), (dx, dy) in itertools.product(rings, dirs):  # near first, then farther
            off = (dx * (marker_pt + pad_points) * scale, dy * (marker_pt + pad_points) * scale)
            ha = {1: "left", -1: "right", 0: "center"}[dx]
            va = {1: "bottom", -1: "top", 0: "center"}[dy]
            ann = ax.annotate(text, (x, y), xytext=off, textcoords="offset points", ha=ha, va=va,
                              fontsize=fontsize, annotation_clip=True, zorder=6,
                              bbox=dict(boxstyle="square,pad=0.1", facecolor="white", alpha=0.7, linewidth=0),
                              arrowprops=dict(arrowstyle="-", lw=0.5, color="0.4", shrinkA=0, shrinkB=3)
                              if leader else None)
            ann.set_in_layout(False)
            b = ann.get_window_extent(renderer)
            inside = frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 and b.y1 <= frame.y1
            hit = (boxes[:, 0] < b.x1) & (boxes[:, 2] > b.x0) & (boxes[:, 1] < b.y1) & (boxes[:, 3] > b.y0)
            if inside and not hit.any():
                out.append(ann)
                pad = 0.5 * fontsize * to_px  # labels keep apart by half an em
                boxes = np.vstack([boxes, [b.x0 - pad, b.y0 - pad, b.x1 + pad, b.y1 + pad]])
                break
            ann.remove()
    return out


def caption(study: Any) -> str:
    """The line under a study's chart: its command, settings and machine (`study`: a :class:`Study`)."""
    return f"{study.command()} · {study.mode} settings · {study.machine()}"
