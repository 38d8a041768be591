"""Accuracy against cost (Pareto), for our model and the three baselines, measured in one run.

    python experiments/pareto.py                 # reduced settings (< 30 min on 2 CPU cores)
    python experiments/pareto.py --full          # model sizes up to the default width 256, default training
    python experiments/pareto.py --quadrature-ckpt outputs/pendulum/runs/<run>/checkpoints/last.ckpt

Hydra multiruns of `python -m lnf.train` (each method across its own size knob: our width, depth, K
and latent dimension; the black box's field width; POD's number of modes k = 1…8; the full-order grid)
and of `python -m lnf.evaluate`: on our reference model, Gauss–Legendre 4²…32² against uniform 16²…64²
quadrature inside the reduced dynamics, integrator and time step; on each width of ours, the tabulated
pullback (``dynamics=tabulated``, RK4 at dt = 0.05 and 0.1, midpoint-4 at 0.05); on each black box, RK4
at dt = 0.1 as well as its trained 0.05. Writes ``pareto.csv``, ``pareto.png`` (test extrapolation
`field_rel_l2` against the latent rollout's wall-clock per trajectory, against rollout plus decoding on
the 64×64 test grid, and against training wall-clock; Pareto fronts marked), ``quadrature.png`` and
``summary.md`` into outputs/studies/pareto/.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import studylib as S  # noqa: E402

ERR = "field_rel_l2/extrapolation/median"
COST = "cost_seconds"  # rollout + decoding of one trajectory's fields at the data's sample times (see add_cost)


def fill_frames(rows: list[dict]) -> None:
    """Output frames of runs that predate the `frames` metric: lnf.train evaluates at every stored sample time."""
    import yaml

    for r in rows:
        if "frames" not in r and "train_seconds" in r:
            cfg = yaml.safe_load((S.ROOT / r["dir"] / ".hydra" / "config.yaml").read_text())
            r["frames"] = float(cfg["data"]["n_times"])


def add_cost(rows: list[dict], frames: int) -> None:
    """cost = latent rollout + decoding scaled to `frames` output frames per trajectory.

    A run with a larger dt decodes fewer frames; scaling its decoding to the data's frame count keeps the
    comparison at equal output (its rollout saving from fewer steps is real and kept)."""
    for r in rows:
        if "decode_seconds_per_trajectory" in r and "frames" in r:
            r[COST] = float(r["rollout_seconds_per_trajectory"]) + float(r["decode_seconds_per_trajectory"]) * frames / float(
                r["frames"])


def sweeps(study: S.Study) -> None:
    smoke, full = study.mode == "smoke", study.mode == "full"
    widths = "32,64,128,256" if full else "16" if smoke else "32,64,128"
    study.multirun("lnf_width", study.method("lnf", [f"model.width={widths}"]), label={"method": "lnf", "knob": "width"})
    if not smoke:
        study.multirun("lnf_depth", study.method("lnf", ["model.depth=1,3"]), label={"method": "lnf", "knob": "depth"})
        study.multirun("lnf_K", study.method("lnf", ["model.reduction_steps=1,5"]), label={"method": "lnf", "knob": "K"})
        study.multirun("lnf_latent", study.method("lnf", ["model.latent_dim=2"]), label={"method": "lnf", "knob": "d"})
    study.multirun("latent_mlp_width", study.method("latent_mlp", [f"model.width={widths}"]),
                   label={"method": "latent_mlp", "knob": "width"})
    modes = "1,2" if smoke else "1,2,3,4,5,6,7,8"
    study.multirun("pod_modes", study.method("pod", [f"model.latent_dim={modes}"]), label={"method": "pod", "knob": "k"})
    res = "12" if smoke else "32,64"
    study.multirun("full_order_grid", study.method("full_order", [f"model.resolution={res}"]),
                   label={"method": "full_order", "knob": "resolution"})


def reference_checkpoint(study: S.Study) -> Path:
    """Our model at the study's reference size (width 64 reduced, 256 full) from the width sweep."""
    want = {"smoke": 16, "reduced": 64, "full": 256}[study.mode]
    for r in study.rows:
        if r["sweep"] == "lnf_width" and int(r.get("model.width", -1)) == want:
            return S.ROOT / r["dir"] / "checkpoints" / "last.ckpt"
    raise RuntimeError(f"no width-{want} run of our model in {study.out}")


def evaluation_sweeps(study: S.Study, ckpt: Path, prefix: str, label: dict) -> None:
    smoke = study.mode == "smoke"
    common = [f"ckpt_path={ckpt}", "figures=0", f"threads={study.threads}"]
    gl = "2,4" if smoke else "4,8,12,16,32" if study.mode == "reduced" and not prefix else "4,6,8,12,16,24,32"
    uni = "4" if smoke else "16,32" if study.mode == "reduced" else "16,32,64"
    study.multirun(f"{prefix}quad_gl", [*common, "quadrature=gauss_legendre", f"quadrature.order={gl}"], "lnf.evaluate",
                   {**label, "knob": "quadrature", "quadrature": "gauss_legendre"})
    if prefix:  # a given (default-size) checkpoint: the Gauss–Legendre sweep only (uniform 64² at width 256 takes long)
        return
    study.multirun(f"{prefix}quad_uniform", [*common, "quadrature=uniform", f"quadrature.resolution={uni}"],
                   "lnf.evaluate", {**label, "knob": "quadrature", "quadrature": "uniform"})
    dts = "0.05" if smoke else "0.05,0.1"
    study.multirun("integrator_midpoint", [*common, "integrator=implicit_midpoint", "integrator.order=2,4", f"dt={dts}"],
                   "lnf.evaluate", {**label, "knob": "integrator"})
    study.multirun("integrator_rk4", [*common, "integrator=rk4", f"dt={dts}"], "lnf.evaluate",
                   {**label, "knob": "integrator"})
    if not smoke:
        study.multirun("integrator_dopri5", [*common, "integrator=dopri5"], "lnf.evaluate",
                       {**label, "knob": "integrator"})


def checkpoints(study: S.Study, sweep: str) -> list[tuple[int, Path]]:
    """(width, last.ckpt) of each run of a training sweep of this study."""
    return [(int(r["model.width"]), S.ROOT / r["dir"] / "checkpoints" / "last.ckpt")
            for r in study.rows if r["sweep"] == sweep and "model.width" in r]


def tabulated_sweeps(study: S.Study) -> None:
    """Our width sweep rolled out with the tabulated pullback (``dynamics=tabulated``: M̃ and Ṽ as Chebyshev
    interpolants on the training codes' range, built once per model) and the black box at the same time steps.

    Both run RK4 at dt = 0.05 (the data's spacing, the black box's training step) and 0.1, so the two are
    compared at equal integrator and step; ours also with the 4th-order midpoint rule at 0.05."""
    smoke = study.mode == "smoke"
    common = ["figures=0", f"threads={study.threads}"]
    dts = "0.05" if smoke else "0.05,0.1"
    for width, ckpt in checkpoints(study, "lnf_width"):
        label = {"method": "lnf", "knob": "tabulated", "model.width": width, "dynamics": "tabulated"}
        study.multirun(f"tabulated_rk4_w{width}", [*common, f"ckpt_path={ckpt}", "dynamics=tabulated",
                                                     "integrator=rk4", f"dt={dts}"], "lnf.evaluate", label)
        if not smoke:
            study.multirun(f"tabulated_midpoint_w{width}", [*common, f"ckpt_path={ckpt}", "dynamics=tabulated",
                                                              "integrator=implicit_midpoint", "integrator.order=4"],
                           "lnf.evaluate", label)
    if smoke:
        return
    for width, ckpt in checkpoints(study, "latent_mlp_width"):  # its training run is RK4 at dt = 0.05
        study.multirun(f"latent_mlp_dt_w{width}", [*common, f"ckpt_path={ckpt}", "integrator=rk4", "dt=0.1"],
                       "lnf.evaluate", {"method": "latent_mlp", "knob": "dt", "model.width": width})


def n_quadrature_points(row: dict) -> float:
    if row.get("quadrature") == "uniform":
        return float(row["quadrature.resolution"]) ** 2
    return float(row["quadrature.order"]) ** 2


def smallest_quadrature(rows: list[dict]) -> dict:
    """The Gauss–Legendre rule with the fewest points whose field_rel_l2 is within 10 % of the finest rule's."""
    gl = sorted((r for r in rows if r.get("quadrature") == "gauss_legendre"), key=n_quadrature_points)
    converged = float(gl[-1]["field_rel_l2/all/median"])
    for r in gl:
        if abs(float(r["field_rel_l2/all/median"]) - converged) <= 0.1 * converged:
            return {"order": int(r["quadrature.order"]), "points": n_quadrature_points(r),
                    "field_rel_l2": float(r["field_rel_l2/all/median"]), "converged": converged,
                    "converged_order": int(gl[-1]["quadrature.order"])}
    return {}


ROLLOUT = "rollout_seconds_per_trajectory"
VARIANT_KNOBS = ("quadrature", "integrator", "dt")  # re-evaluations of a trained model: hollow markers


def cost_panels() -> list[tuple[str, str]]:
    return [(ROLLOUT, "latent rollout wall-clock per trajectory [s] (5 s horizon, 16 at once)"),
            (COST, "rollout + decoding per trajectory [s] (64×64 grid, all sample times)"),
            ("train_seconds", "training wall-clock [s] (incl. closed-form fits)")]


def plot(study: S.Study, rows: list[dict]) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    train_rows = [r for r in rows if "train_seconds" in r and r["sweep"].split("_")[0] in ("lnf", "latent", "pod", "full")]
    fig, axes = plt.subplots(1, 3, figsize=(19, 5.5))
    for ax, (xkey, xlabel) in zip(axes, cost_panels()):
        pts = train_rows if xkey == "train_seconds" else [r for r in rows if not r["sweep"].startswith("ref_")]
        x = np.array([float(r.get(xkey, np.nan)) for r in pts])
        y = np.array([float(r.get(ERR, np.nan)) for r in pts])
        for m in S.METHODS:
            sel = [i for i, r in enumerate(pts) if S.method_of(r) == m]
            if not sel:
                continue
            tabulated = [i for i in sel if pts[i].get("knob") == "tabulated"]
            variants = [i for i in sel if pts[i].get("knob") in VARIANT_KNOBS]
            core = [i for i in sel if i not in variants and i not in tabulated]
            ax.scatter(x[core], y[core], c=S.COLORS[m], marker=S.MARKERS[m], s=50, label=S.LABELS[m], zorder=3)
            if variants:
                ax.scatter(x[variants], y[variants], facecolors="none", edgecolors=S.COLORS[m], marker=S.MARKERS[m],
                           s=40, label=f"{S.LABELS[m]}: quadrature / integrator / dt variants", zorder=3)
            if tabulated:
                ax.scatter(x[tabulated], y[tabulated], c=S.COLORS[m], marker="*", s=90, zorder=4,
                           label=f"{S.LABELS[m]}, tabulated M̃, Ṽ (dynamics=tabulated)")
            for i in core + tabulated:
                knob = pts[i].get("knob")
                key = {"width": "model.width", "depth": "model.depth", "K": "model.reduction_steps",
                       "d": "model.latent_dim", "k": "model.latent_dim", "resolution": "model.resolution",
                       "tabulated": "model.width"}.get(knob)
                if key and key in pts[i]:
                    text = f"{knob}={pts[i][key]}" if knob != "tabulated" else (
                        f"w={pts[i][key]} {pts[i].get('integrator', 'midpoint')} {pts[i].get('dt') or ''}")
                    ax.annotate(text, (x[i], y[i]), fontsize=6, xytext=(3, 3), textcoords="offset points")
        front = S.pareto_mask(x, y)
        order = np.argsort(x[front])
        ax.step(x[front][order], y[front][order], where="post", color="k", lw=1, ls="--", label="Pareto front", zorder=2)
        for m in ("lnf", "latent_mlp"):  # each method's own front: the acceptance compares these two
            sel = np.array([S.method_of(r) == m for r in pts])
            if sel.any():
                own = S.pareto_mask(np.where(sel, x, np.nan), np.where(sel, y, np.nan))
                order = np.argsort(x[own])
                ax.step(x[own][order], y[own][order], where="post", color=S.COLORS[m], lw=0.8, ls=":", zorder=2,
                        label=f"front of {S.LABELS[m]}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(xlabel, fontsize=8)
        ax.set_ylabel("test field_rel_l2, extrapolation (t ≥ 2.5 s), median")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=6, loc="best")
    fig.suptitle(f"Accuracy vs cost, {study.scene} — {S.caption(study, 'python experiments/pareto.py')}", fontsize=9)
    out = [S.save_figure(fig, study.out / "pareto.png")]

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for prefix, name in [("", "width-64 model of this study"), ("ref_", "--quadrature-ckpt model")]:
        for kind, style in [("gauss_legendre", "o-"), ("uniform", "s--")]:
            sel = sorted((r for r in rows if r["sweep"].startswith(f"{prefix}quad_") and r.get("quadrature") == kind
                          and (prefix or not r["sweep"].startswith("ref_"))), key=n_quadrature_points)
            if sel:
                ax.plot([n_quadrature_points(r) for r in sel], [float(r["field_rel_l2/all/median"]) for r in sel], style,
                        label=f"{kind.replace('_', '–')} ({name})")
    ax.set_xlabel("quadrature points inside the reduced dynamics")
    ax.set_ylabel("test field_rel_l2 (all), median")
    S.log_axes(ax)
    ax.set_title(f"Quadrature of the reduced dynamics ({study.scene})", fontsize=9)
    out.append(S.save_figure(fig, study.out / "quadrature.png"))
    return out


def summary(study: S.Study, rows: list[dict]) -> Path:
    core = [r for r in rows if r.get("knob") not in (*VARIANT_KNOBS, "tabulated")]
    lnf = [r for r in rows if S.method_of(r) == "lnf" and not r["sweep"].startswith("ref_")]
    bb = [r for r in rows if S.method_of(r) == "latent_mlp"]

    def dominance(key: str, ours: list[dict]) -> str:
        lc = np.array([float(r.get(key, np.nan)) for r in ours])
        le = np.array([float(r.get(ERR, np.nan)) for r in ours])
        flags = [S.dominates(lc, le, float(r[key]), float(r[ERR])) for r in bb]
        missed = [f"width {r.get('model.width')} dt {r.get('dt') or 0.05}" for r, f in zip(bb, flags) if not f]
        return f"{sum(flags)}/{len(flags)}" + (f" (not: {', '.join(missed)})" if missed else "")

    exact = [r for r in lnf if r.get("knob") != "tabulated"]
    fom = [r for r in rows if S.method_of(r) == "full_order" and int(r.get("model.resolution", 0)) == 64]
    ref = [r for r in lnf if r.get("knob") == "width" and int(r.get("model.width", 0)) ==
           {"smoke": 16, "reduced": 64, "full": 256}[study.mode]]
    lines = [f"# Pareto study ({study.scene}, {study.mode} settings)\n",
             f"Machine: {study.machine()}. Command: `python experiments/pareto.py{'' if study.mode == 'reduced' else ' --' + study.mode}`.\n",
             f"Cost = `{COST}`: latent rollout over the 5 s horizon + decoding at every sample time on the 64×64 test grid,"
             " per trajectory, 16 rolled out at once (runs with a larger dt decode fewer frames: their decoding is scaled"
             " to the same frame count);"
             f" error = test `{ERR}`.\n",
             "\nBlack-box points dominated by one of our points (cost ≤ and extrapolation error ≤):\n",
             f"- on latent rollout cost (`{ROLLOUT}`): {dominance(ROLLOUT, lnf)} with every point of ours; "
             f"{dominance(ROLLOUT, exact)} without the tabulated ones;\n",
             f"- on rollout + decoding cost (`{COST}`): {dominance(COST, lnf)} with every point of ours; "
             f"{dominance(COST, exact)} without the tabulated ones.\n"]
    if fom and ref:
        lines.append(f"\nFull-order model on the 64×64 grid: {S.fmt(fom[0][COST])} s per trajectory (rollout "
                     f"{S.fmt(fom[0]['rollout_seconds_per_trajectory'])} s); our reference model: "
                     f"{S.fmt(ref[0][COST])} s (rollout {S.fmt(ref[0]['rollout_seconds_per_trajectory'])} s): ratio ours/full "
                     f"= {float(ref[0][COST]) / float(fom[0][COST]):.3g}.\n")
    for prefix, name in [("", "reference model"), ("ref_", "given checkpoint")]:
        quad = [r for r in rows if r["sweep"].startswith(f"{prefix}quad_") and (prefix or not r["sweep"].startswith("ref_"))]
        if quad:
            best = smallest_quadrature(quad)
            if best:
                lines.append(f"\nSmallest Gauss–Legendre rule within 10 % of the {best['converged_order']}² result "
                             f"({S.fmt(best['converged'])}) on the {name}: {best['order']}² = {int(best['points'])} points "
                             f"({S.fmt(best['field_rel_l2'])}).\n")
    cols = [("sweep", "sweep"), ("method", "method"), ("knob", "knob"), ("model.width", "width"),
            ("model.depth", "depth"), ("model.reduction_steps", "K"), ("model.latent_dim", "d / k"),
            ("model.resolution", "grid"), ("quadrature.order", "GL order"), ("quadrature.resolution", "uniform res"),
            ("integrator", "integrator"), ("integrator.order", "order"), ("dt", "dt"),
            ("field_rel_l2/in_horizon/median", "err in-horizon"), (ERR, "err extrapolation"),
            ("dynamics", "dynamics"), ("table_nodes", "table nodes"), ("table_seconds", "table build s"),
            ("table_fallback_fraction", "off-table share"),
            ("energy_drift/max", "energy drift"), ("rollout_seconds_per_trajectory", "rollout s/traj"),
            (COST, "rollout+decode s/traj"), ("train_seconds", "train s")]
    lines.append("\n" + S.markdown_table(core + [r for r in rows if r not in core], cols))
    return S.write_text_atomic(study.out / "summary.md", "".join(lines))


def main(argv=None) -> None:
    def extra(p):
        p.add_argument("--quadrature-ckpt", type=Path, default=None,
                       help="also sweep the quadrature on this checkpoint (e.g. the default model of the main experiment)")

    study, args = S.parse_args("pareto", __doc__, argv, extra)
    sweeps(study)
    tabulated_sweeps(study)
    label = {"method": "lnf"}
    evaluation_sweeps(study, reference_checkpoint(study), "", label)
    if args.quadrature_ckpt:
        evaluation_sweeps(study, args.quadrature_ckpt.resolve(), "ref_", {"method": "lnf", "reference": "given"})
    rows = study.rows
    fill_frames(rows)
    add_cost(rows, max(int(float(r["frames"])) for r in rows if "frames" in r))
    csv_path = study.write_csv("pareto.csv")
    study.finish([csv_path, *plot(study, rows), summary(study, rows)])


if __name__ == "__main__":
    main()
