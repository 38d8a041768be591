"""The figures of ``python -m experiments.scenes``: ours against the full-order reference over time, at the point that
moves most, the valid prediction times of ours and the black box, the error against the number of linear modes, the
deformed 3-D body."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import numpy as np

from experiments import studylib
from lnf import metrics as M
from lnf.plotting import _subscript, save_figure


def figure() -> tuple[Any, Any]:
    """A figure and axes of the studies' size, drawn without a display."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(5.8, 4.2), layout="constrained")


def ours_against_reference(times: np.ndarray, ours: np.ndarray, reference: np.ndarray, ylabel: str, title: str,
                           path: Path, horizon: float | None = None, n: int = 3) -> Path:
    """One quantity (n_traj, T) over time for the first `n` trajectories, ours (solid) and the reference's
    (dotted)."""
    from matplotlib.lines import Line2D

    fig, ax = figure()
    shown = min(n, len(ours))
    for i in range(shown):
        ax.plot(times, reference[i], color=f"C{i}", ls=":", lw=1.8)
        ax.plot(times, ours[i], color=f"C{i}", lw=1.3, alpha=0.9)
    handles = [Line2D([], [], color="0.3", lw=1.3, label="ours"),
               Line2D([], [], color="0.3", ls=":", lw=1.8, label="full-order reference")]
    if horizon is not None:
        ax.axvline(horizon, color="k", ls="--", lw=0.8)
        handles.append(Line2D([], [], color="k", ls="--", lw=0.8, label="training horizon"))
    handles += [Line2D([], [], color=f"C{i}", lw=4, label=f"test trajectory {i}") for i in range(shown)]
    ax.set_xlabel("time t [s]")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=9)
    studylib.legend_outside(ax, "below", handles=handles, ncols=3)
    return save_figure(fig, path)


def probe(evaluation: Any) -> tuple[int, int]:
    """(point, component) of the evaluation's true field that moves most over time (its largest standard deviation
    in time, averaged over the trajectories): the free end of a cantilever, the middle of a string."""
    motion = np.nan_to_num(np.asarray(evaluation.true_fields, dtype=np.float64)).std(axis=1).mean(axis=0)  # (N, A)
    point, component = np.unravel_index(int(np.argmax(motion)), motion.shape)
    return int(point), int(component)


def probe_figure(ev: Any, path: Path, title: str, horizon: float | None = None,
                 at: Optional[tuple[int, int]] = None) -> Path:
    """The field at the point (and component) that moves most (`at`, default :func:`probe`) over time, ours against
    the full-order reference's."""
    point, component = probe(ev) if at is None else at
    where = ", ".join(f"{x:.3g}" for x in ev.points[point])
    return ours_against_reference(ev.times, ev.pred_fields[:, :, point, component],
                                  ev.true_fields[:, :, point, component],
                                  f"field component q{_subscript(component + 1)} at X = ({where})", title, path,
                                  horizon)


def energy_figure(ev: Any, scale: float, title: str, path: Path, horizon: float | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The total energy over `scale` of an evaluation, ours against the reference's; returns both (n, T)."""
    e = ev.energies
    pred, true = e["kinetic_pred"] + e["potential_pred"], e["kinetic_true"] + e["potential_true"]
    ours_against_reference(ev.times, pred / scale, true / scale, "total energy / E_scale", title, path, horizon)
    return pred, true


def vpt_per_trajectory(evaluation: Any) -> np.ndarray:
    """`vpt` of every trajectory (the metrics hold only its median and min)."""
    w = np.full(len(evaluation.points), 1.0 / len(evaluation.points))
    return M.valid_prediction_time(evaluation.pred_fields, evaluation.true_fields, w, evaluation.times)


def vpt_histogram(ours: Any, black_box: Any, horizon: float, path: Path) -> Path:
    """The valid prediction time of each test trajectory, ours against the black box's (``vpt.png``)."""
    vpt_ours, vpt_bb = vpt_per_trajectory(ours), vpt_per_trajectory(black_box)
    fig, ax = figure()
    ax.hist([vpt_ours, vpt_bb], bins=10, color=[studylib.COLORS["lnf"], studylib.COLORS["latent_mlp"]],
            label=[f"ours (median {np.median(vpt_ours):.2f} s)", f"black box (median {np.median(vpt_bb):.2f} s)"])
    ax.axvline(horizon, color="k", ls="--", lw=0.8, label="training horizon")
    ax.set_xlabel(studylib.metric_label("vpt") + " of each test trajectory")
    ax.set_ylabel("test trajectories")
    ax.grid(alpha=0.3, axis="y")
    studylib.legend_outside(ax, "below", ncols=2)
    return save_figure(fig, path)


def modes_figure(pod_rows: list[dict[str, Any]], oracle: list[float], d: int, ours_err: float, path: Path) -> Path:
    """The test error of POD-Galerkin with k modes and of the best linear k-mode projection, against ours
    (``modes.png``)."""
    max_modes = len(oracle)
    fig, ax = figure()
    ks = [r["k"] for r in pod_rows]
    ax.semilogy(ks, [r["field_rel_l2/all/median"] for r in pod_rows], "s-", color=studylib.COLORS["pod"], alpha=0.85,
                label="POD-Galerkin rollout")
    ax.semilogy(range(1, max_modes + 1), oracle, "k:", marker=".", label="best linear k-mode projection (full-grid SVD)")
    ax.semilogy([d], [ours_err], "o", ms=9, color=studylib.COLORS["lnf"], label=f"ours, d = {d} ({ours_err:.3f})",
                zorder=4)
    ax.axhline(ours_err, color=studylib.COLORS["lnf"], lw=0.8, ls="--")
    ax.set_xlabel("modes k (POD) / latent dimension d (ours)")
    ax.set_xticks(range(1, max_modes + 1))
    ax.set_ylabel(studylib.metric_label("field_rel_l2/all/median", wrap=True))
    ax.grid(alpha=0.3, which="both")
    studylib.legend_outside(ax, "below", ncols=1)
    return save_figure(fig, path)


def shape_figure(ev: Any, horizon: float, path: Path) -> np.ndarray:
    """The deformed body (the evaluation points moved to X + u, coloured by the displacement's size) of the first
    trajectory of `ev`, the reference's above ours, at four times; returns the indices of those times."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    times = ev.times
    picks = np.unique(np.linspace(1, len(times) - 1, 4).round().astype(int))
    X = np.asarray(ev.points, dtype=np.float64)
    fields = {"full-order reference": ev.true_fields[0], "ours": ev.pred_fields[0]}
    scale = float(np.nanmax(np.linalg.norm(ev.true_fields[0], axis=-1)))
    lo, hi = (X + np.nan_to_num(ev.true_fields[0]).min(0)).min(0), (X + np.nan_to_num(ev.true_fields[0]).max(0)).max(0)
    fig = plt.figure(figsize=(3.1 * len(picks), 5.4), layout="constrained")
    for row, (label, u) in enumerate(fields.items()):
        for col, k in enumerate(picks):
            ax = fig.add_subplot(2, len(picks), row * len(picks) + col + 1, projection="3d")
            Y = X + u[k]
            art = ax.scatter(Y[:, 0], Y[:, 1], Y[:, 2], c=np.linalg.norm(u[k], axis=-1), s=3, cmap="viridis",
                             vmin=0.0, vmax=scale, depthshade=False)
            ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]), xlabel="x₁ [m]", ylabel="x₂ [m]",
                   zlabel="x₃ [m]")
            ax.set_box_aspect(hi - lo)
            ax.view_init(elev=18, azim=-60)
            ax.tick_params(labelsize=6, pad=0)
            ax.locator_params(axis="y", nbins=2)
            ax.locator_params(axis="z", nbins=3)
            side = "before" if times[k] < horizon else "after"
            ax.set_title(f"{label}\nt = {times[k]:.2f} s ({side} the horizon)", fontsize=8)
    fig.colorbar(art, ax=fig.axes, shrink=0.6, label="displacement ‖u‖ [m]")
    fig.suptitle(f"test trajectory 0: the deformed body (points X + u), dt = {times[1] - times[0]:g} s", fontsize=9)
    save_figure(fig, path)
    return picks
