"""Accuracy against cost (Pareto), for our model and the three baselines, measured in one run.

    python -m experiments.pareto                 # reduced settings (< 30 min on 2 CPU cores)
    python -m experiments.pareto --full          # model sizes up to the default width 256, default training
    python -m experiments.pareto --quadrature-ckpt outputs/pendulum/runs/<run>/checkpoints/last.ckpt
    python -m experiments.pareto --scene elastic # any conf/experiment/<scene>.yaml: outputs/studies/pareto-<scene>
    PYTHONPATH=examples python -m experiments.pareto --config-dir examples/conf --scene vibrating_string  # your own

Hydra multiruns of `python -m lnf.train` (each method across its own size knob: our width, depth, K
and latent dimension; the black box's field width; POD's number of modes k = 1…8; the full-order grid)
and of `python -m lnf.evaluate`: on our reference model, Gauss–Legendre 4²…32² against uniform 16²…64²
quadrature inside the reduced dynamics, integrator and time step; on each width of ours, the tabulated
pullback (``dynamics=tabulated``, RK4 at dt = 0.05 and 0.1, midpoint-4 at 0.05); on each black box, RK4
at dt = 0.1 as well as its trained 0.05. Writes ``pareto.csv``, ``pareto.png`` (test extrapolation
`field_rel_l2` against the latent rollout's wall-clock per trajectory, against rollout plus decoding on
the 64×64 test grid, and against training wall-clock; Pareto fronts marked), ``quadrature.png`` and
``summary.md`` into outputs/studies/pareto/.

On the other scenes (`--scene`), ours sweeps its width only (their latent dimension is model_size.py's
study), methods a scene cannot run are left out (as its `Scene.baselines()` says), a scene that trains with
the tabulated pullback gets the exact one as its variant, and on a scene whose full-order reference is itself
costly (`Scene.expensive_reference`: the elastic scenes' FEM) the simulator's own cost per trajectory, measured
in the same run, is drawn as the full-order line.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lnf.tabulated import force_separates

from experiments import operator_inference as OI
from experiments import studylib as S

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


def architecture_knobs(study: S.Study) -> bool:
    """Whether this study sweeps our depth, K and latent dimension as well as the width: on the default
    experiment only (the paper's pendulum, studylib.default_experiment). The other scenes chart the width sweep
    (their latent dimension is model_size.py's question), which keeps each scene's study near 30 min on 2 cores."""
    return study.mode != "smoke" and study.is_default_scene()


def sweeps(study: S.Study) -> None:
    smoke, full = study.mode == "smoke", study.mode == "full"
    for m in S.METHODS:
        if not study.supports(m):
            print(f"[{study.name}] {S.LABELS[m]} left out: scene {study.scene!r} cannot run it (its baselines() says "
                  f"{m}: False)", flush=True)
    widths = "32,64,128,256" if full else "16" if smoke else "32,64,128"
    study.multirun("lnf_width", study.method("lnf", [f"model.width={widths}"]), label={"method": "lnf", "knob": "width"})
    if architecture_knobs(study):
        study.multirun("lnf_depth", study.method("lnf", ["model.depth=1,3"]), label={"method": "lnf", "knob": "depth"})
        study.multirun("lnf_K", study.method("lnf", ["model.reduction_steps=1,5"]), label={"method": "lnf", "knob": "K"})
        study.multirun("lnf_latent", study.method("lnf", ["model.latent_dim=2"]), label={"method": "lnf", "knob": "d"})
    if study.supports("latent_mlp"):
        study.multirun("latent_mlp_width", study.method("latent_mlp", [f"model.width={widths}"]),
                       label={"method": "latent_mlp", "knob": "width"})
    modes = "1,2" if smoke else "1,2,3,4,5,6,7,8"
    study.multirun("pod_modes", study.method("pod", [f"model.latent_dim={modes}"]), label={"method": "pod", "knob": "k"})
    if study.supports("full_order"):
        res = "12" if smoke else "32,64"
        study.multirun("full_order_grid", study.method("full_order", [f"model.resolution={res}"]),
                       label={"method": "full_order", "knob": "resolution"})
    if study.supports("opinf"):  # fitted here, on the same dataset, at POD's numbers of modes
        OI.study_rows(study, [int(k) for k in modes.split(",")])  # r = 2k: POD-Galerkin's state dimension


def reference_checkpoint(study: S.Study) -> Path:
    """Our model at the study's reference size (width 64 reduced, 256 full) from the width sweep."""
    want = {"smoke": 16, "reduced": 64, "full": 256}[study.mode]
    for r in study.rows:
        if r["sweep"] == "lnf_width" and int(r.get("model.width", -1)) == want:
            return S.ROOT / r["dir"] / "checkpoints" / "last.ckpt"
    raise RuntimeError(f"no width-{want} run of our model in {study.out}")


MAX_QUADRATURE_POINTS = 4096  # a rule of more points per evaluation job is left out (32³ on a 3-D body: 24 GB)


def _within_points(study: S.Study, per_axis: str, what: str) -> str:
    """The comma-separated points-per-axis counts of `per_axis` whose rule on the scene's body has at most
    MAX_QUADRATURE_POINTS points (each count to the power of the body's dimension); the others are named as left out."""
    dim = study.scene_object().body_dim
    counts = [int(n) for n in per_axis.split(",")]
    kept = [n for n in counts if n ** dim <= MAX_QUADRATURE_POINTS] or counts[:1]  # never an empty sweep
    dropped = [n for n in counts if n not in kept]
    if dropped:
        print(f"[{study.name}] {what} {', '.join(map(str, dropped))} left out: more than {MAX_QUADRATURE_POINTS} "
              f"points on a {dim}-D body", flush=True)
    return ",".join(map(str, kept))


def evaluation_sweeps(study: S.Study, ckpt: Path, prefix: str, label: dict) -> None:
    smoke = study.mode == "smoke"
    common = [f"ckpt_path={ckpt}", "figures=0", f"threads={study.threads}"]
    gl = "2,4" if smoke else "4,8,12,16,32" if study.mode == "reduced" and not prefix else "4,6,8,12,16,24,32"
    uni = "4" if smoke else "16,32" if study.mode == "reduced" else "16,32,64"
    gl, uni = (_within_points(study, rule, name) for rule, name in ((gl, "Gauss–Legendre orders"),
                                                                      (uni, "uniform resolutions")))
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


def experiment_dynamics(study: S.Study) -> str:
    """The dynamics config the scene experiment selects (``tabulated`` for the elastic cantilever, else the
    default ``lagrangian``)."""
    return str(study.composed().hydra.runtime.choices.dynamics)


def tabulated_sweeps(study: S.Study) -> None:
    """Our width sweep rolled out with the other pullback and the black box at the same time steps.

    The other pullback is the tabulated one (``dynamics=tabulated``: M̃ and Ṽ as Chebyshev interpolants on the
    training codes' range, built once per model) where the scene trains with the exact one, and the exact one
    (``dynamics=lagrangian``) where the scene experiment already tabulates (the elastic cantilever). Both run RK4
    at dt = 0.05 (the data's spacing, the black box's training step) and 0.1, so the two are compared at equal
    integrator and step; ours also with the 4th-order midpoint rule at 0.05."""
    smoke = study.mode == "smoke"
    common = ["figures=0", f"threads={study.threads}"]
    dts = "0.05" if smoke else "0.05,0.1"
    other = "lagrangian" if experiment_dynamics(study) == "tabulated" else "tabulated"
    knob = "exact" if other == "lagrangian" else "tabulated"
    widths = checkpoints(study, "lnf_width")
    if other == "tabulated" and widths and not force_separates(study.scene_object()):
        print(f"[{study.name}] no tabulated variant: {study.scene}'s damping or loads do not separate (the table "
              "needs a conservative scene or GeneralizedForce.separated())", flush=True)
        widths = []
    for width, ckpt in widths:
        label = {"method": "lnf", "knob": knob, "model.width": width, "dynamics": other}
        study.multirun(f"{knob}_rk4_w{width}", [*common, f"ckpt_path={ckpt}", f"dynamics={other}",
                                                  "integrator=rk4", f"dt={dts}"], "lnf.evaluate", label)
        if not smoke:
            study.multirun(f"{knob}_midpoint_w{width}", [*common, f"ckpt_path={ckpt}", f"dynamics={other}",
                                                           "integrator=implicit_midpoint", "integrator.order=4"],
                           "lnf.evaluate", label)
    if smoke:
        return
    for width, ckpt in checkpoints(study, "latent_mlp_width"):  # its training run is RK4 at dt = 0.05
        study.multirun(f"latent_mlp_dt_w{width}", [*common, f"ckpt_path={ckpt}", "integrator=rk4", "dt=0.1"],
                       "lnf.evaluate", {"method": "latent_mlp", "knob": "dt", "model.width": width})


def closure_sweeps(study: S.Study) -> None:
    """Our width sweep re-evaluated with a potential closure fitted on each model's training trajectories first
    (``lnf.evaluate closure_degree=4``, method §5.6): the method "lnf_closure", at the same widths; under --smoke
    the first width only, its residual fit alone (a one-epoch model's stiff trial rollouts cost seconds each; the
    shooting has tests of its own, tests/test_closure.py)."""
    widths = checkpoints(study, "lnf_width")
    smoke = study.mode == "smoke"
    for width, ckpt in widths[:1] if smoke else widths:
        study.multirun(f"closure_w{width}", ["figures=0", f"threads={study.threads}", f"ckpt_path={ckpt}",
                                             "closure_degree=4", *(["closure_shooting_iterations=0"] if smoke else [])],
                       "lnf.evaluate",
                       {"method": "lnf_closure", "knob": "width", "model.width": width})


def simulator_seconds(ckpt: Path, threads: int, trust: list[str] | None = None, frames: int | None = None) -> dict:
    """Wall-clock per test trajectory of the scene's own full-order simulator over the test horizon (on a scene
    with an expensive reference, e.g. the elastic scenes' FEM), measured in this run (the faster of two): the
    ground truth, so its error is 0. `frames`: only the first ones of the horizon (the smoke mode's check)."""
    import torch

    from lnf.model import load
    from experiments.scenes import snapshot_data_of, timed

    torch.set_num_threads(threads)
    model = load(ckpt, trust=trust)
    split = snapshot_data_of(model).split("test")
    times = split.times[:frames]
    seconds, _ = timed(lambda: model.scene.simulate(split.states[:, 0], times))
    return {"simulator_seconds_per_trajectory": seconds / len(split.states), "trajectories": len(split.states),
            "horizon_s": float(times[-1] + times[1] - times[0])}


def n_quadrature_points(row: dict, dim: int = 2) -> float:
    """Points of a quadrature sweep's rule on a `dim`-D body (its order or resolution per axis, to the dim)."""
    if row.get("quadrature") == "uniform":
        return float(row["quadrature.resolution"]) ** dim
    return float(row["quadrature.order"]) ** dim


def smallest_quadrature(rows: list[dict], dim: int = 2) -> dict:
    """The Gauss–Legendre rule with the fewest points whose field_rel_l2 is within 10 % of the finest rule's."""
    gl = sorted((r for r in rows if r.get("quadrature") == "gauss_legendre"), key=n_quadrature_points)
    converged = float(gl[-1]["field_rel_l2/all/median"])
    for r in gl:
        if abs(float(r["field_rel_l2/all/median"]) - converged) <= 0.1 * converged:
            return {"order": int(r["quadrature.order"]), "points": n_quadrature_points(r, dim),
                    "field_rel_l2": float(r["field_rel_l2/all/median"]), "converged": converged,
                    "converged_order": int(gl[-1]["quadrature.order"])}
    return {}


ROLLOUT = "rollout_seconds_per_trajectory"
VARIANT_KNOBS = ("quadrature", "integrator", "dt")  # re-evaluations of a trained model: hollow markers
# our width sweep re-evaluated with the pullback the scene does not train with: knob → (marker, legend)
OTHER_PULLBACK = {"tabulated": ("*", "tabulated M̃, Ṽ (dynamics=tabulated)"),
                  "exact": ("P", "exact pullback (dynamics=lagrangian)")}
DIVERGED_AT = 10.0


def cost_panels() -> list[tuple[str, str]]:
    return [(ROLLOUT, S.metric_label(ROLLOUT) + "\n(latent rollout only, all test trajectories at once)"),
            (COST, S.metric_label(COST) + "\n(the test grid, every sample time)"),
            ("train_seconds", S.metric_label("train_seconds") + "\n(incl. closed-form fits)")]


SHORT_INTEGRATOR = {"implicit_midpoint": "midpoint", "rk4": "RK4", "dopri5": "dopri5"}


def point_label(row: dict, dim: int = 2) -> str:
    """A compact name of a point for the chart: "w64", "k 2", "64²", "w64 tab. RK4 0.1", "GL 8²", "RK4 dt 0.1"."""
    knob = row.get("knob")
    get = lambda key: None if row.get(key) in (None, "") else S.fmt(row[key])  # noqa: E731
    integ = get("integrator")
    integ = SHORT_INTEGRATOR.get(str(integ), str(integ)) if integ else None
    if integ == "midpoint" and get("integrator.order") == "4":
        integ = "midpoint-4"
    dt = f"dt {get('dt')}" if get("dt") else None
    width = f"w{get('model.width')}" if get("model.width") else None
    if knob == "width":
        return width or "width"
    if knob in ("depth", "K", "d", "k", "r"):
        key = {"depth": "model.depth", "K": "model.reduction_steps", "d": "model.latent_dim", "k": "model.latent_dim",
               "r": "rank"}
        return f"{knob} = {get(key[knob])}"
    if knob == "resolution":
        return S.per_axis(get("model.resolution"), dim)
    if knob in OTHER_PULLBACK:
        return " ".join(p for p in (width, "tab." if knob == "tabulated" else "exact", integ, dt) if p)
    if knob == "quadrature":
        if get("quadrature.order"):
            return f"GL {S.per_axis(get('quadrature.order'), dim)}"
        return f"uniform {S.per_axis(get('quadrature.resolution'), dim)}"
    return " ".join(p for p in (width if S.method_of(row) == "latent_mlp" else None, integ, dt) if p) or "variant"


def _suptitle(fig, text: str, study: S.Study) -> None:
    fig.suptitle(f"{text}\n{S.caption(study)}", fontsize=9)


def plot(study: S.Study, rows: list[dict], simulator: dict | None = None) -> list[Path]:
    plt = S.pyplot()

    dim = study.scene_object().body_dim
    train_rows = [r for r in rows if "train_seconds" in r
                  and r["sweep"].split("_")[0] in ("lnf", "latent", "pod", "full", "opinf")]  # opinf_rank: both OpInfs
    fig, axes = plt.subplots(1, 3, figsize=(15, 6.2), layout="constrained", sharey=True)
    to_label = []
    for ax, (xkey, xlabel) in zip(axes, cost_panels()):
        pts = train_rows if xkey == "train_seconds" else [r for r in rows if not r["sweep"].startswith("ref_")]
        x = np.array([float(r.get(xkey, np.nan)) for r in pts])
        y = np.array([float(r.get(ERR, np.nan)) for r in pts])
        shown_y = np.where(np.isfinite(y), y, DIVERGED_AT)
        for m in S.CHARTED:
            sel = [i for i, r in enumerate(pts) if S.method_of(r) == m]
            if not sel:
                continue
            other = [i for i in sel if pts[i].get("knob") in OTHER_PULLBACK]
            variants = [i for i in sel if pts[i].get("knob") in VARIANT_KNOBS]
            core = [i for i in sel if i not in variants and i not in other]
            ok = lambda idx: [i for i in idx if np.isfinite(y[i])]  # noqa: E731
            if ok(core):  # (no legend entry for what is not drawn)
                ax.scatter(x[ok(core)], y[ok(core)], c=S.COLORS[m], marker=S.MARKERS[m], s=55, label=S.LABELS[m],
                           zorder=4, alpha=0.9, edgecolors="white", linewidths=0.6)
            if ok(variants):
                ax.scatter(x[ok(variants)], y[ok(variants)], facecolors="none", edgecolors=S.COLORS[m],
                           marker=S.MARKERS[m], s=45, linewidths=1.1, zorder=3, alpha=0.8,
                           label=f"{S.LABELS[m]}: quadrature / integrator / dt variants")
            for knob, (marker, text) in OTHER_PULLBACK.items():
                pick = ok([i for i in other if pts[i].get("knob") == knob])
                if pick:
                    ax.scatter(x[pick], y[pick], c=S.COLORS[m], marker=marker, s=95, zorder=4, alpha=0.85,
                               edgecolors="white", linewidths=0.6, label=f"{S.LABELS[m]}, {text}")
            failed = [i for i in sel if np.isfinite(x[i]) and not np.isfinite(y[i])]
            if failed:  # a diverged rollout's error is inf: drawn in a band at the top
                ax.scatter(x[failed], np.full(len(failed), DIVERGED_AT), c=S.COLORS[m], marker="X", s=60, zorder=4,
                           alpha=0.8, edgecolors="k", linewidths=0.5,
                           label=f"{S.LABELS[m]}: diverged (drawn at {DIVERGED_AT:g})")
        if np.any(np.isfinite(x) & ~np.isfinite(y)):
            ax.axhspan(DIVERGED_AT / 1.7, DIVERGED_AT * 1.7, color="0.92", zorder=0, lw=0)
        front = S.pareto_mask(x, y)
        order = np.argsort(x[front])
        ax.step(x[front][order], y[front][order], where="post", color="k", lw=1.1, ls="--", zorder=2,
                label="Pareto front" if front.sum() > 1 else None)  # one point: no line to name
        labelled = set(np.flatnonzero(front))
        for m in S.CHARTED:  # each method's own front; the acceptance compares ours with the black box's
            sel = np.array([S.method_of(r) == m for r in pts])
            if not sel.any():
                continue
            own = S.pareto_mask(np.where(sel, x, np.nan), np.where(sel, y, np.nan))
            labelled |= set(np.flatnonzero(own))
            if m in ("lnf", "latent_mlp"):
                order = np.argsort(x[own])
                ax.step(x[own][order], y[own][order], where="post", color=S.COLORS[m], lw=0.9, ls=":", zorder=2,
                        label=f"front of {S.LABELS[m]}" if own.sum() > 1 else None)
        if simulator and xkey != "train_seconds":
            ax.axvline(simulator["simulator_seconds_per_trajectory"], color="tab:gray", lw=1.2,
                       label=f"the scene's full-order simulator (ground truth, error 0), "
                             f"{simulator['simulator_seconds_per_trajectory']:.3g} s")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.grid(True, which="major", alpha=0.35)
        ax.grid(True, which="minor", alpha=0.12)
        keep = sorted(labelled, key=lambda i: x[i])
        to_label.append((ax, [x[i] for i in keep], [y[i] for i in keep], [point_label(pts[i], dim) for i in keep],
                         list(zip(x, shown_y))))
    axes[0].set_ylabel(S.metric_label(ERR, wrap=True))
    for ax in axes:
        S.readable_log_ticks(ax)
    S.figure_legend(fig, axes, ncols=3)
    _suptitle(fig, f"Accuracy against cost, {study.scene} (labels: the points on a Pareto front)", study)
    for ax, xs, ys, texts, avoid in to_label:  # after the layout is final: measured where they will be drawn
        S.place_labels(ax, xs, ys, texts, fontsize=7.5, avoid=avoid)
    out = [S.save_figure(fig, study.out / "pareto.png")]

    fig, ax = plt.subplots(figsize=(6.4, 5.0), layout="constrained")
    width = {"smoke": 16, "reduced": 64, "full": 256}[study.mode]  # reference_checkpoint's
    models = [("", f"width-{width} model of this study"), ("ref_", "--quadrature-ckpt model")]
    for k, (prefix, name) in enumerate(models):
        for kind, marker, ls, dodge in [("gauss_legendre", "o", "-", 0.97), ("uniform", "s", "--", 1.03)]:
            sel = sorted((r for r in rows if r["sweep"].startswith(f"{prefix}quad_") and r.get("quadrature") == kind
                          and (prefix or not r["sweep"].startswith("ref_"))), key=n_quadrature_points)
            if sel:  # uniform hollow and a little to the right: a rule with the same points and error stays visible
                err = np.array([float(r["field_rel_l2/all/median"]) for r in sel])
                S.plot_marking_failures(ax, np.array([n_quadrature_points(r, dim) for r in sel]) * dodge, err,
                                        ~np.isfinite(err), marker=marker, ls=ls,
                                        color=f"C{2 * k + (kind == 'uniform')}",
                                        markerfacecolor="white" if kind == "uniform" else None,
                                        markeredgecolor=None if kind == "uniform" else "white", markeredgewidth=1.2,
                                        label=f"{'Gauss–Legendre' if kind == 'gauss_legendre' else 'uniform'} "
                                              f"({name})")
    ax.set_xlabel("quadrature points inside the reduced dynamics")
    ax.set_ylabel(S.metric_label("field_rel_l2/all/median", wrap=True))
    S.log_axes(ax, legend="none")
    S.ticks_at(ax, [n_quadrature_points(r, dim) for r in rows if "quad_" in r["sweep"]])
    S.figure_legend(fig, [ax], ncols=1)
    ax.set_title(f"Quadrature of the reduced dynamics, {study.scene}\n(a diverged rollout: × at 10)", fontsize=10)
    out.append(S.save_figure(fig, study.out / "quadrature.png"))
    return out


def describe(row: dict, dim: int = 2) -> str:
    """A short name of one point's settings (width, k or grid; the re-evaluation's dynamics, integrator and dt) on a
    `dim`-D body."""
    if row.get("knob") == "r":  # Operator Inference: its POD rank (twice the latent dimension it stands beside)
        return f"r {row['rank']}"
    parts = [f"{k} {row[key]}" for k, key in [("width", "model.width"), ("depth", "model.depth"),
                                                ("K", "model.reduction_steps"), ("d/k", "model.latent_dim"),
                                                ("grid", "model.resolution")] if row.get(key) not in (None, "")]
    if row.get("knob") in (*VARIANT_KNOBS, *OTHER_PULLBACK):
        parts += [str(row.get(k)) for k in ("dynamics", "integrator") if row.get(k)]
        parts += [f"order {row['integrator.order']}"] if row.get("integrator.order") else []
        parts += [f"dt {row['dt']}"] if row.get("dt") else []
        parts += [f"GL {S.per_axis(row['quadrature.order'], dim)}"] if row.get("quadrature.order") else []
        parts += [f"uniform {S.per_axis(row['quadrature.resolution'], dim)}"] if row.get("quadrature.resolution") else []
    return ", ".join(parts) or "default"


def best_of_each_method(rows: list[dict], dim: int = 2) -> list[dict]:
    """Per method, its most accurate row: the cheapest (rollout + decoding) of those within 1 % of its lowest finite
    extrapolation error, so that ties (POD beyond the modes a scene has) name the smallest model. None where every
    run diverged."""
    out = []
    for m in S.CHARTED:
        mine = [r for r in rows if S.method_of(r) == m and not r["sweep"].startswith("ref_")
                and np.isfinite(float(r.get(ERR, np.nan)))]
        if mine:
            lowest = min(float(r[ERR]) for r in mine)
            best = min((r for r in mine if float(r[ERR]) <= 1.01 * lowest), key=lambda r: float(r.get(COST, np.inf)))
            out.append({**best, "label": S.LABELS[m], "setting": describe(best, dim)})
    return out


def against_operator_inference(rows: list[dict], latent_dim: int) -> str:
    """A paragraph comparing our most accurate point after the horizon with Operator Inference (on the full states,
    and on lnf's sparse observations) at the same state dimension (rank r = 2d: q̃ and q̃̇) and at its best, saying
    plainly which is ahead ("" without OpInf rows)."""
    def finite(m: str) -> list[dict]:
        return [r for r in rows if S.method_of(r) == m and not r["sweep"].startswith("ref_")
                and np.isfinite(float(r.get(ERR, np.nan)))]

    ours = finite("lnf") + finite("lnf_closure")
    if not ours or not any(S.method_of(r).startswith("opinf") for r in rows):
        return ""
    best = min(ours, key=lambda r: float(r[ERR]))
    d = int(best.get("model.latent_dim") or latent_dim)
    text = f"\nAgainst Operator Inference: our most accurate point after the horizon has {S.fmt(best[ERR])} at d = {d}."
    for m, reads in (("opinf", "the full fine-grid training states"), ("opinf_observed", "lnf's sparse observations")):
        op = finite(m)
        tried = [r for r in rows if S.method_of(r) == m]
        if not tried:
            continue
        same = [r for r in op if int(r["model.latent_dim"]) == d]
        text += f" OpInf on {reads}"
        if same:
            ratio = float(best[ERR]) / float(same[0][ERR])
            text += (f", at r = {2 * d} (the same state dimension): {S.fmt(same[0][ERR])}; ours is {S.fmt(ratio)}× "
                     f"its error: " + ("**lnf loses**" if ratio > 1 else "**lnf is ahead**"))
        if op:
            top = min(op, key=lambda r: float(r[ERR]))
            text += (f"; its best {S.fmt(top[ERR])} at r = {top['rank']} (fit {S.fmt(top['train_seconds'])} s, rollout "
                     f"+ decoding {S.fmt(top.get(COST))} s per trajectory).")
        else:
            text += ": every rank tried diverged."
    return text + "\n"


def summary(study: S.Study, rows: list[dict], simulator: dict | None = None) -> Path:
    core = [r for r in rows if r.get("knob") not in (*VARIANT_KNOBS, *OTHER_PULLBACK)]
    lnf = [r for r in rows if S.method_of(r) == "lnf" and not r["sweep"].startswith("ref_")]
    bb = [r for r in rows if S.method_of(r) == "latent_mlp"]
    dim = study.scene_object().body_dim

    def dominance(key: str, ours: list[dict]) -> str:
        lc = np.array([float(r.get(key, np.nan)) for r in ours])
        le = np.array([float(r.get(ERR, np.nan)) for r in ours])
        flags = [S.dominates(lc, le, float(r[key]), float(r[ERR])) for r in bb]
        missed = [f"width {r.get('model.width')} dt {r.get('dt') or 0.05}" for r, f in zip(bb, flags) if not f]
        return f"{sum(flags)}/{len(flags)}" + (f" (not: {', '.join(missed)})" if missed else "")

    if experiment_dynamics(study) == "tabulated":  # the scene trains with the table: its exact points are variants
        exact, exact_text = [r for r in lnf if r.get("knob") == "exact"], "with the exact pullback's points only"
    else:
        exact, exact_text = [r for r in lnf if r.get("knob") != "tabulated"], "without the tabulated ones"
    fom = [r for r in rows if S.method_of(r) == "full_order" and int(r.get("model.resolution", 0)) == 64]
    ref = [r for r in lnf if r.get("knob") == "width" and int(r.get("model.width", 0)) ==
           {"smoke": 16, "reduced": 64, "full": 256}[study.mode]]
    lines = [f"# Pareto study ({study.scene}, {study.mode} settings)\n",
             f"Machine: {study.machine()}. Command: `{study.command()}`. Body dimension: {dim}.\n",
             f"Cost = `{COST}`: latent rollout over the test horizon + decoding at every sample time on the test grid,"
             " per trajectory, all test trajectories rolled out at once (runs with a larger dt decode fewer frames: their"
             " decoding is scaled to the same frame count);"
             f" error = test `{ERR}`.\n"]
    if bb:
        lines += ["\nBlack-box points dominated by one of our points (cost ≤ and extrapolation error ≤):\n",
                  f"- on latent rollout cost (`{ROLLOUT}`): {dominance(ROLLOUT, lnf)} with every point of ours; "
                  f"{dominance(ROLLOUT, exact)} {exact_text};\n",
                  f"- on rollout + decoding cost (`{COST}`): {dominance(COST, lnf)} with every point of ours; "
                  f"{dominance(COST, exact)} {exact_text}.\n"]
    else:
        lines.append("\nNo black-box latent MLP: it cannot run this scene (the scene's baselines() says so).\n")
    left_out = [S.LABELS[m] for m in S.CHARTED if m != "latent_mlp" and not study.supports(m)]
    if left_out:
        lines.append(f"\nLeft out, as the scene's baselines() says they cannot run it: {', '.join(left_out)}.\n")
    if simulator and ref:
        sim = simulator["simulator_seconds_per_trajectory"]
        lines.append(f"\nThe scene's full-order simulator (the ground truth), measured in this run: {S.fmt(sim)} s per "
                     f"trajectory over {S.fmt(simulator['horizon_s'])} s ({simulator['trajectories']} test trajectories). "
                     f"Our reference model (width {ref[0]['model.width']}): rollout {S.fmt(ref[0][ROLLOUT])} s, "
                     f"{S.fmt(sim / float(ref[0][ROLLOUT]))}× faster; with decoding {S.fmt(ref[0][COST])} s, "
                     f"{S.fmt(sim / float(ref[0][COST]))}× faster.\n")
    if fom and ref:
        lines.append(f"\nFull-order model on the 64×64 grid: {S.fmt(fom[0][COST])} s per trajectory (rollout "
                     f"{S.fmt(fom[0]['rollout_seconds_per_trajectory'])} s); our reference model: "
                     f"{S.fmt(ref[0][COST])} s (rollout {S.fmt(ref[0]['rollout_seconds_per_trajectory'])} s): ratio ours/full "
                     f"= {float(ref[0][COST]) / float(fom[0][COST]):.3g}.\n")
    lines.append(against_operator_inference(rows, int(study.composed().model.get("latent_dim") or 1)))
    lines.append("\nMost accurate point of each method (extrapolation error; its costs and energy drift):\n\n"
                 + S.markdown_table(best_of_each_method(rows, dim), [
                     ("label", "method"), ("setting", "setting"), (ERR, "err extrapolation"),
                     ("field_rel_l2/in_horizon/median", "err in-horizon"), ("energy_drift/max", "energy drift"),
                     (ROLLOUT, "rollout s/traj"), (COST, "rollout+decode s/traj"), ("train_seconds", "train s")]))
    for prefix, name in [("", "reference model"), ("ref_", "given checkpoint")]:
        quad = [r for r in rows if r["sweep"].startswith(f"{prefix}quad_") and (prefix or not r["sweep"].startswith("ref_"))]
        if quad:
            best = smallest_quadrature(quad, dim)
            if best:
                lines.append(f"\nSmallest Gauss–Legendre rule within 10 % of the "
                             f"{S.per_axis(best['converged_order'], dim)} result ({S.fmt(best['converged'])}) on the "
                             f"{name}: {S.per_axis(best['order'], dim)} = {int(best['points'])} points "
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
    # no long-horizon energy check in the training jobs: no chart or table of this study reads it (energy over long
    # horizons is stability.py's), and on stiff pullbacks it cost up to an hour per job (POD-Galerkin k >= 5)
    study.long_check = False
    sweeps(study)
    tabulated_sweeps(study)
    closure_sweeps(study)
    label = {"method": "lnf"}
    evaluation_sweeps(study, reference_checkpoint(study), "", label)
    if args.quadrature_ckpt:
        evaluation_sweeps(study, args.quadrature_ckpt.resolve(), "ref_", {"method": "lnf", "reference": "given"})
    rows = study.rows
    fill_frames(rows)
    add_cost(rows, max(int(float(r["frames"])) for r in rows if "frames" in r))
    simulator = None
    if study.scene_object().expensive_reference:  # measured with the sweeps: reused with them, unless --fresh
        stored = study.out / "simulator.json"
        if stored.is_file() and not study.fresh:
            simulator = json.loads(stored.read_text())
        else:
            simulator = simulator_seconds(reference_checkpoint(study), study.threads, study.trusted_modules(),
                                          frames=3 if study.mode == "smoke" else None)
            S.write_text_atomic(stored, json.dumps(simulator, indent=1))
    csv_path = study.write_csv("pareto.csv")
    study.finish([csv_path, *plot(study, rows, simulator), summary(study, rows, simulator)])


if __name__ == "__main__":
    main()
