"""The public figures: :func:`latent_and_energy_figure`, :func:`field_snapshots_figure`, :func:`figure3`."""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure, SubFigure

from lnf.plotting.checks import (
    _check_bounds, _check_box, _check_fields, _check_grid_shape, _check_grid_shape_nd, _check_latent, _check_points,
    _check_scalar, _check_series, _check_times)
from lnf.plotting.energy import _draw_latent_energy
from lnf.plotting.fields import _draw_fields, _draw_fields_1d, _draw_scattered_body
from lnf.plotting.style import ENERGY_KEYS, _X_LABELS


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
