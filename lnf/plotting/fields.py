"""The field panels of Figure 3: predicted, true and error snapshots on grids, scattered points, 1-D and 3-D bodies."""
from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure, SubFigure

from lnf.plotting.style import (
    _ERROR_CMAP, _ERROR_LABEL, _ERROR_PERCENTILE, _FIELD_CMAP, _MASK_COLOR, _X_LABELS, _format_t)


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


def _snapshot_panels(fig, pred: np.ndarray, true: np.ndarray):
    """The 3 × S panels (predicted, true, error) of S snapshots and what they share: S, the error |pred − true| (NaN
    where either is NaN), the field and error colour limits with their colour-bar extensions, the two colour maps
    (non-finite values grey), the axes (3, S)."""
    import matplotlib as mpl

    S = pred.shape[0]
    err = np.abs(pred - true)
    cmap_f = mpl.colormaps[_FIELD_CMAP].with_extremes(bad=_MASK_COLOR)
    cmap_e = mpl.colormaps[_ERROR_CMAP].with_extremes(bad=_MASK_COLOR)
    axes = np.asarray(fig.subplots(3, S, sharex=True, sharey=True, squeeze=False))
    return S, err, _field_scale(pred, true), _error_scale(err), cmap_f, cmap_e, axes


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
    S, err, (vmax, f_extend), (emax, e_extend), cmap_f, cmap_e, axes = _snapshot_panels(fig, pred, true)
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
    tri = _triangulate(xy, what)
    pred = np.where(np.isfinite(pred), pred, np.nan)
    true = np.where(np.isfinite(true), true, np.nan)
    S, err, (vmax, f_extend), (emax, e_extend), cmap_f, cmap_e, axes = _snapshot_panels(fig, pred, true)
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
