"""Stability where methods fail: long horizons, high energy, large time steps, resolution transfer.

    python -m experiments.stability           # reduced settings (< 30 min on 2 CPU cores)
    python -m experiments.stability --full    # default model size and training budget
    PYTHONPATH=examples python -m experiments.stability --config-dir examples/conf --scene vibrating_string  # your own

Trains each method once with `python -m lnf.train` (our model, the black-box latent MLP, POD-Galerkin
with k = 1, the full-order model on the 64×64 grid), then re-evaluates each checkpoint with Hydra
multiruns of `python -m lnf.evaluate`:

- long horizons: 20× and 200× the training horizon (50 s and 500 s at a 0.05 s step), energy drift and
  vpt per method and integrator (200×: sampled every 0.5 s, integrated at 0.05 s);
- high energy: the scene's release cases (`Scene.stability_cases()`; skipped, with a note in the output and
  in summary.md, on a scene that has none): on the pendulum θ0 = 0.5π (edge of the training range) … 0.99π
  at rest, and one rotating pendulum above the separatrix (θ0 = 0, θ̇0 = 7 rad/s); both links of the double
  pendulum at θ0, the bump's pendulum as the pendulum's, the cantilever released at rest from tip deflections
  0.15 m (edge of the training range) … 0.4 m;
- large time steps: dt = 0.05 … 0.8 s (over 4.8 s of the 5 s data, a whole number of each) until each method and
  integrator fails (a trajectory diverges, or its error exceeds max(2 × its own dt = 0.05 error, 0.05));
- resolution transfer: trained on 25 % of 32×32, evaluated on 16², 64², 128² and 4096 random points (a 3-D
  body on 8³, 16³, 32³).

A run that diverges is a data point (marked ×), not a crash. `--parts` runs some of the four questions only
(e.g. `--parts high_energy dt`; the others' panels say "not run"). Writes stability.csv, stability.png and
summary.md into outputs/studies/stability/.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Optional, Sequence

import numpy as np

from experiments import studylib as S

if TYPE_CHECKING:
    from lnf.scenes.base import StabilityCases

INTEGRATORS = {"lnf": ["implicit_midpoint", "rk4"], "latent_mlp": ["rk4"], "pod": ["implicit_midpoint", "rk4"],
               "full_order": ["implicit_midpoint", "rk4"]}
SHORT = {"implicit_midpoint": "midpoint-4", "rk4": "RK4"}
PARTS = ("long", "high_energy", "dt", "resolution")  # the study's questions, as `--parts` names them


INLINE_STATE_SIZE = 8  # larger full-order states (the elastic mesh) go to lnf.evaluate as .npy files


def dt_sweep_horizon(study: Any, dts: str) -> str:
    """The horizon [s] of the large-step sweep: the data's (n_times × dt), cut to a whole number of the largest step
    (0.05 … 0.8 s steps doubling: then a whole number of each), so that lnf.evaluate rolls every step out over the
    same window (5 s data: 4.8 s)."""
    data = study.composed().data
    largest = max(float(x) for x in dts.split(","))
    horizon = float(data.n_times) * float(data.dt)
    return f"{math.floor(horizon / largest + 1e-9) * largest:.6g}"


def stress_cases(study: S.Study) -> Optional[StabilityCases]:
    """The scene's high-energy release cases (``Scene.stability_cases()``), or None: no high-energy part."""
    return study.scene_object().stability_cases()


def skipped_high_energy(study: S.Study) -> str:
    """Why the study has no high-energy part (the scene declares no release cases), and what would add it: "no
    high-energy part: <why>; <what to define>"."""
    scene = study.scene_object()
    cases = "return a lnf.scenes.StabilityCases (the levels, their label, the edge of the training range) from " \
            "the scene's stability_cases() to run them"
    if scene.capabilities()["release_at_rest"]:
        return (f"no high-energy part: scene {study.scene!r} defines released_at_rest() but no stability_cases(), "
                f"so the study does not know which release amplitudes lie beyond its training range; {cases}")
    return (f"no high-energy part: scene {study.scene!r} defines neither released_at_rest() nor stability_cases(); "
            f"define released_at_rest(amplitude) and {cases}")


def initial_state_arguments(study: S.Study, scene: Any, cases: StabilityCases,
                            levels: Sequence[float]) -> dict[str, float]:
    """`initial_states=` values for lnf.evaluate → their level: inline lists for small states, else .npy files
    written into the study's folder."""
    out = {}
    for level in levels:
        state = cases.states(scene, level)
        if state.size <= INLINE_STATE_SIZE:
            out[_inline(state)] = level
        else:
            path = study.out / "initial_states" / f"high_energy_{level:g}.npy"
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(path.stem + ".tmp.npy")
            np.save(tmp, state[None])
            tmp.replace(path)
            out[str(path)] = level
    return out


def methods(study: S.Study) -> list[str]:
    """The methods of studylib.METHODS that can run the study's scene."""
    return [m for m in S.METHODS if study.supports(m)]


def train_all(study: S.Study) -> dict[str, Path]:
    ckpts = {}
    for m in methods(study):
        rows = study.multirun(f"train_{m}", study.method(m), label={"method": m, "study": "train"})
        ckpts[m] = S.ROOT / rows[0]["dir"] / "checkpoints" / "last.ckpt"
    return ckpts


def evaluations(study: S.Study, ckpts: dict[str, Path], parts: Sequence[str] = PARTS) -> None:
    """One multirun per (question, integrator), sweeping the checkpoints of every method that integrator applies to;
    `parts`: the questions of PARTS to ask."""
    smoke = study.mode == "smoke"
    by_path = {str(p): m for m, p in ckpts.items()}
    scene = study.scene_object()
    cases = stress_cases(study) if "high_energy" in parts else None
    if cases is None and "high_energy" in parts:
        print(f"[{study.name}] {skipped_high_energy(study)}", flush=True)
    expensive = scene.expensive_reference
    before = len(study.rows)
    dts = "0.05,0.2" if smoke else "0.05,0.1,0.2,0.4,0.8"
    dt_horizon = dt_sweep_horizon(study, dts) if "dt" in parts else None  # one composed config, both integrators
    for integ in ("implicit_midpoint", "rk4"):
        paths = ",".join(str(ckpts[m]) for m in ckpts if integ in INTEGRATORS[m])
        common = [f"ckpt_path={paths}", "figures=0", f"threads={study.threads}", f"integrator={integ}"]
        lab = {"integrator_name": integ}
        # long horizons (20× and 200× the 2.5 s training horizon)
        h20, h200 = ("1.0", "2.0") if smoke else ("50", "500")
        if "long" in parts:
            study.multirun(f"long20_{integ}", [*common, f"horizon={h20}", "dt=0.05", "max_trajectories=4",
                                               "grid.kind=uniform", "grid.resolution=32"], "lnf.evaluate",
                           {**lab, "study": "long", "horizon_factor": 20})
            if not smoke and expensive:  # energy drift of 10 000 steps: no 500 s full-order reference per job
                study.multirun(f"long200_{integ}", [*common, "long_steps=10000", "long_trajectories=4"], "lnf.evaluate",
                               {**lab, "study": "long", "horizon_factor": 200})
            elif not smoke:
                study.multirun(f"long200_{integ}", [*common, f"horizon={h200}", "dt=0.5", "integrator.substeps=10",
                                                    "max_trajectories=4", "grid.kind=uniform", "grid.resolution=32"],
                               "lnf.evaluate", {**lab, "study": "long", "horizon_factor": 200})
        # high energy and beyond the training range
        if cases is not None:
            levels = cases.levels[:2] if smoke else cases.levels
            values = initial_state_arguments(study, scene, cases, levels)
            before_energy = len(study.rows)
            study.multirun(f"energy_{integ}", [*common, f"initial_states={','.join(values)}"], "lnf.evaluate",
                           {**lab, "study": "high_energy"})
            for row in study.rows[before_energy:]:
                row["stress_level"] = values[_state_key(row["initial_states"])]
            if cases.rotation is not None and not smoke:
                study.multirun(f"rotation_{integ}", [*common, "initial_states=[[" + ",".join(map(str, cases.rotation))
                                                     + "]]"], "lnf.evaluate", {**lab, "study": "rotation"})
        # large time steps
        if "dt" in parts:
            study.multirun(f"dt_{integ}", [*common, f"dt={dts}", f"horizon={dt_horizon}",
                                           f"max_trajectories={2 if smoke else 8}"], "lnf.evaluate",
                           {**lab, "study": "dt"})
        # resolution transfer, with each method's first integrator
        own = ",".join(str(ckpts[m]) for m in ckpts if INTEGRATORS[m][0] == integ)
        if own and "resolution" in parts:
            res = transfer_resolutions(scene.body_dim, smoke)
            base = [f"ckpt_path={own}", "figures=0", f"threads={study.threads}", f"integrator={integ}"]
            study.multirun(f"grid_{integ}", [*base, "grid.kind=uniform", f"grid.resolution={res}"], "lnf.evaluate",
                           {**lab, "study": "resolution"})
            study.multirun(f"random_{integ}", [*base, "grid.kind=random", f"grid.n_points={256 if smoke else 4096}"],
                           "lnf.evaluate",
                           {**lab, "study": "resolution"})
    for row in study.rows[before:]:
        row["method"] = by_path[str(row["ckpt_path"])]


def transfer_resolutions(dim: int, smoke: bool = False) -> str:
    """The uniform grids of the resolution transfer, points per axis: 16, 64, 128 (a 3-D body 8, 16, 32: 128³ points
    of 16 trajectories × 100 frames would be 40 GB of fields; 32³ is 32 768 points)."""
    if smoke:
        return "8"
    return "8,16,32" if dim >= 3 else "16,64,128"


def grid_name(row: dict, dim: int) -> str:
    """The evaluation grid of a resolution-transfer row: "64²" (a uniform grid of a 2-D body; "64 points" in 1-D,
    "64³" in 3-D) or "random"."""
    if row.get("grid.kind") != "uniform":
        return "random"
    return S.per_axis(row["grid.resolution"], dim) + (" points" if dim == 1 else "")


def _inline(state: Sequence[float]) -> str:
    """One full-order state as an `initial_states=` value on the command line."""
    return "[[" + ",".join(f"{float(x):.6f}" for x in state) + "]]"


def _state_key(value: Any) -> str:
    """The `initial_states=` argument a row was evaluated with, as written on the command line."""
    return _inline(value[0]) if isinstance(value, list) else str(value)


def _drift(row: dict) -> float:
    """Energy drift of a long-horizon row: over its rollout, or over its `long_steps` run (no ground truth)."""
    return float(row.get("energy_drift/max", row.get("energy_drift_long/max", np.nan)))


def _energy_error(row: dict) -> float:
    """A long-horizon row's energy error against the reference's energy (a damped or loaded scene, whose energy
    changes by the forces' work: its drift is physics, not an error); NaN for a `long_steps` check, which has no
    reference over its horizon (its energy_rel_err is the default test horizon's)."""
    value = row.get("energy_rel_err/max")
    if row.get("energy_drift_long/max") not in (None, "") or value in (None, ""):
        return np.nan
    return float(value)


def long_energy(study: S.Study) -> tuple[Callable[[dict], float], str]:
    """What the long-horizon part reads of a row's energy, and that metric's key: the drift on a conservative
    scene, the error against the reference's energy on a damped or loaded one."""
    if study.scene_object().is_conservative:
        return _drift, "energy_drift/max"
    return _energy_error, "energy_rel_err/max"


def _level(row: dict) -> float:
    return float(row.get("stress_level", np.nan))


def _diverged(rows: list[dict]) -> np.ndarray:
    return np.array([float(r.get("diverged_fraction", 0)) > 0 for r in rows], bool)


def failure_dt(rows: list[dict]) -> float:
    """Largest dt before the first failure: a diverged trajectory, or an error above max(2 × the smallest dt's, 0.05)."""
    rows = sorted(rows, key=lambda r: float(r["dt"]))
    base = float(rows[0]["field_rel_l2/all/median"])
    ok = np.nan
    for r in rows:
        err = float(r["field_rel_l2/all/median"])
        if float(r.get("diverged_fraction", 0)) > 0 or not np.isfinite(err) or err > max(2 * base, 0.05):
            break
        ok = float(r["dt"])
    return ok


STYLES = {"implicit_midpoint": "-", "rk4": ":"}


def _dodge(x: Any, k: int, n: int, log: bool = False, categorical: bool = False) -> np.ndarray:
    """x of the k-th of n curves moved a little sideways (:func:`studylib.dodged`; on a categorical axis by 0.07 of
    a category per step), so that curves with equal values stay visible."""
    c = k - (n - 1) / 2
    if categorical:
        return np.asarray(x, float) + 0.07 * c
    return S.dodged(x, "", log=log, steps=c)


def _combo_style(m: str, integ: str) -> dict:
    return dict(marker=S.MARKERS[m], color=S.COLORS[m], ls=STYLES[integ], lw=1.5)


def error_lines(ax, rows: list[dict], combos: list[tuple[str, str]], sub_study: str, x_of, log_x: bool = False) -> None:
    """Test field error against x_of(row), one line per (method, integrator) of `sub_study`, failures marked; the
    lines a little apart sideways (see :func:`_dodge`)."""
    for k, (m, integ) in enumerate(combos):
        sel = sorted((r for r in rows if r.get("study") == sub_study and r["method"] == m
                      and r["integrator_name"] == integ), key=x_of)
        if sel:
            S.plot_marking_failures(ax, _dodge([x_of(r) for r in sel], k, len(combos), log_x),
                                    np.array([float(r["field_rel_l2/all/median"]) for r in sel]), _diverged(sel),
                                    **_combo_style(m, integ), label=f"{S.LABELS[m]}, {SHORT[integ]}")


def _horizon_text(rows: list[dict], factor: int) -> str:
    """ "20× the training horizon (50 s)": the factor and what the rows of it rolled out."""
    row = next((r for r in rows if r.get("study") == "long" and int(r["horizon_factor"]) == factor), {})
    if row.get("horizon") not in (None, ""):
        return f"{factor}× the training horizon\n({S.fmt(row['horizon'])} s)"
    if row.get("long_steps") not in (None, ""):
        return f"{factor}× the training horizon\n({S.fmt(row['long_steps'])} steps, no reference)"
    return f"{factor}× the training horizon"


def _say_not_run(ax, part: str) -> None:
    """An empty panel for a question `--parts` left out, saying so."""
    ax.text(0.5, 0.5, f"not run (--parts without {part})", ha="center", va="center", transform=ax.transAxes,
            fontsize=10)
    ax.set_xticks([])
    ax.set_yticks([])


def plot(study: S.Study, rows: list[dict], parts: Sequence[str] = PARTS) -> Path:
    plt = S.pyplot()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    fig, axes = plt.subplots(2, 2, figsize=(13, 10), layout="constrained")
    combos = [(m, i) for m in methods(study) for i in INTEGRATORS[m]]
    n = len(combos)

    ax = axes[0, 0]  # long horizons: energy drift (a damped or loaded scene: energy error) at 20× and 200×
    energy_of, energy_key = long_energy(study)
    factors = sorted({int(r["horizon_factor"]) for r in rows if r.get("study") == "long"}) or [20]
    n_long = max((int(float(r.get("max_trajectories", 4) or 4)) for r in rows if r.get("study") == "long"), default=4)
    for k, (m, integ) in enumerate(combos):
        sel = [next((r for r in rows if r.get("study") == "long" and r["method"] == m and r["integrator_name"] == integ
                     and int(r["horizon_factor"]) == f), None) for f in factors]
        if not any(sel):
            continue
        drift = np.array([energy_of(r) if r else np.nan for r in sel])
        failed = np.array([bool(r) and (float(r.get("diverged_fraction", 0)) > 0 or not np.isfinite(_drift(r)))
                           for r in sel])
        x = _dodge(np.arange(len(factors)), k, n, categorical=True)
        have = np.array([r is not None for r in sel]) & (np.isfinite(drift) | failed)  # no reference: no error
        S.plot_marking_failures(ax, x[have], drift[have], failed[have], **_combo_style(m, integ))
    ax.set_xticks(np.arange(len(factors)), [_horizon_text(rows, f) for f in factors])
    ax.set_xlim(-0.5, len(factors) - 0.5)
    ax.set_yscale("log")
    ax.set_ylabel(S.metric_label(energy_key, over=f"{n_long} trajectories", wrap=True))
    ax.set_title("Long horizons", fontsize=10)
    if "long" not in parts:
        _say_not_run(ax, "long")

    ax = axes[0, 1]
    cases = stress_cases(study)
    if "high_energy" not in parts:
        _say_not_run(ax, "high_energy")
    elif cases is not None:
        levels = [_level(r) for r in rows if r.get("study") == "high_energy"]
        span = (max(levels) - min(levels)) if len(levels) > 1 else 1.0
        error_lines(ax, rows, combos, "high_energy", _level)
        if levels:  # the levels tried, the training range's edge shaded from the left (not from 0: it would fill it)
            lo, hi = min(levels) - 0.08 * span, max(levels) + 0.08 * span
            ax.set_xlim(lo, hi)
            if cases.train_edge > lo:
                ax.axvspan(lo, min(cases.train_edge, hi), color="0.9", zorder=0)
        ax.set_xlabel(cases.xlabel)
        ax.set_ylabel("relative L² field error\n(one released trajectory per point)")
        ax.set_yscale("log")
    else:  # nothing to draw: say why on the panel
        ax.text(0.5, 0.5, "skipped: the scene declares no\nstability_cases() (its release amplitudes)",
                ha="center", va="center", transform=ax.transAxes, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    ax.set_title("High energy, beyond the training range", fontsize=10)

    ax = axes[1, 0]
    n_dt = max((int(float(r.get("max_trajectories", 8) or 8)) for r in rows if r.get("study") == "dt"), default=8)
    error_lines(ax, rows, combos, "dt", lambda r: float(r["dt"]), log_x=True)
    ax.set_xscale("log")
    ax.set_yscale("log")
    S.ticks_at(ax, [r["dt"] for r in rows if r.get("study") == "dt"])
    ax.set_xlabel(S.metric_label("dt"))
    ax.set_ylabel(S.metric_label("field_rel_l2/all/median", split=f"{n_dt} test trajectories", wrap=True))
    ax.set_title("Large time steps (× = diverged in ≥ 1 trajectory)", fontsize=10)
    if "dt" not in parts:
        _say_not_run(ax, "dt")

    ax = axes[1, 1]
    labels: list[str] = []
    dim = study.scene_object().body_dim
    ms = methods(study)
    for k, m in enumerate(ms):
        sel = [r for r in rows if r.get("study") == "resolution" and r["method"] == m]
        sel = sorted(sel, key=lambda r: (r.get("grid.kind") == "random", int(r.get("grid.resolution", 0) or 0)))
        if not sel:
            continue
        names = [grid_name(r, dim).replace("random", f"{int(float(r.get('grid.n_points') or 4096))} random")
                 for r in sel]
        labels = labels if len(labels) >= len(names) else names
        integ = sel[0]["integrator_name"]
        S.plot_marking_failures(ax, _dodge(np.arange(len(sel)), k, len(ms), categorical=True),
                                np.array([float(r["field_rel_l2/all/median"]) for r in sel]), _diverged(sel),
                                **_combo_style(m, integ))
    ax.set_xticks(np.arange(len(labels)), labels)
    ax.set_xlim(-0.5, max(len(labels), 1) - 0.5)
    ax.set_yscale("log")
    ax.set_xlabel("evaluation points (not seen in training)")
    ax.set_ylabel(S.metric_label("field_rel_l2/all/median", wrap=True))
    ax.set_title("Resolution transfer", fontsize=10)
    if "resolution" not in parts:
        _say_not_run(ax, "resolution")
    for ax in axes.ravel():
        ax.grid(True, which="major", alpha=0.35)
        ax.grid(True, which="minor", alpha=0.12)
        S.readable_log_ticks(ax)

    handles = [Line2D([], [], **_combo_style(m, i), markeredgecolor="white", label=f"{S.LABELS[m]}, {SHORT[i]}")
               for m, i in combos]
    handles.append(Line2D([], [], marker="X", color="0.5", markeredgecolor="k", ls="none", markersize=8,
                          label="diverged (drawn at 10)"))
    if cases is not None and "high_energy" in parts:
        handles.append(Patch(color="0.9", label=cases.train_text))
    fig.legend(handles=handles, loc="outside lower center", ncols=4, fontsize="small", frameon=False)
    fig.suptitle(f"Stability, {study.scene} ({S.DODGE_NOTE})\n{S.caption(study)}", fontsize=9)
    return S.save_figure(fig, study.out / "stability.png")


def summary(study: S.Study, rows: list[dict], parts: Sequence[str] = PARTS) -> Path:
    cases = stress_cases(study) if "high_energy" in parts else None
    expensive = study.scene_object().expensive_reference
    levels = sorted({_level(r) for r in rows if r.get("study") == "high_energy"})  # smoke runs the first two only
    highest = f"{levels[-1]:g}: {cases.xlabel}" if cases and levels else "none"
    table = []
    for m in methods(study):
        for integ in INTEGRATORS[m]:
            def pick(st, **kw):
                return [r for r in rows if r.get("study") == st and r["method"] == m and r["integrator_name"] == integ
                        and all(str(r.get(k)) == str(v) for k, v in kw.items())]
            long20, long200 = pick("long", horizon_factor=20), pick("long", horizon_factor=200)
            energy = sorted(pick("high_energy"), key=_level)
            rot = pick("rotation")
            dts = pick("dt")
            table.append({
                "method": S.LABELS[m], "integrator": SHORT[integ],
                "err20": long20[0].get("field_rel_l2/all/median") if long20 else "",
                "energy20": " / ".join(S.fmt(long20[0].get(f"energy_rel_err/{k}")) for k in ("median", "max"))
                if long20 else "",
                "levels": " / ".join(S.fmt(r["field_rel_l2/all/median"]) for r in energy),
                "drift20": long20[0].get("energy_drift/max") if long20 else "",
                "vpt20": long20[0].get("vpt/median") if long20 else "",
                "drift200": _drift(long200[0]) if long200 else "",
                # a costly scene's 200× row measures the energy alone: its vpt would be the default 5 s horizon's
                "vpt200": long200[0].get("vpt/median") if long200 and not expensive else "",
                "err_099": energy[-1]["field_rel_l2/all/median"] if energy else "",
                "err_rot": rot[0]["field_rel_l2/all/median"] if rot else "",
                "max_dt": failure_dt(dts) if dts else "",
            })
    res, grids = [], []
    dim = study.scene_object().body_dim
    for m in methods(study):
        row = {"method": S.LABELS[m]}
        for r in sorted((r for r in rows if r.get("study") == "resolution" and r["method"] == m),
                        key=lambda r: (r.get("grid.kind") == "random", int(r.get("grid.resolution", 0) or 0))):
            key = grid_name(r, dim)
            row[key] = r["field_rel_l2/all/median"]
            grids += [key] if key not in grids else []
        res.append(row)
    if study.scene_object().is_conservative:
        columns = [("method", "method"), ("integrator", "integrator"), ("drift20", "energy drift 20×"),
                   ("vpt20", "vpt 20× [s]"), ("drift200", "energy drift 200×"), ("vpt200", "vpt 200× [s]")]
        if cases is not None:  # without release cases the high-energy columns would stay empty
            columns += [("err_099", f"err at the highest level ({highest})"), ("err_rot", "err rotation")]
    else:  # damped or loaded: the energy changes by the forces' work, so its error is against the reference's
        columns = [("method", "method"), ("integrator", "integrator"), ("err20", "field error 20×"),
                   ("vpt20", "vpt 20× [s]"), ("energy20", "energy error vs the reference 20×: median / max")]
        if cases is not None:
            columns += [("levels", f"err at {' / '.join(f'{v:g}' for v in levels)} ({cases.xlabel})")]
    skipped = "" if cases or "high_energy" not in parts else skipped_high_energy(study)
    only = "" if tuple(parts) == PARTS else f" --parts {' '.join(parts)}"
    left_out = [p for p in PARTS if p not in parts]
    text = [f"# Stability study ({study.scene}, {study.mode} settings)\n\n",
            f"Machine: {study.machine()}. Command: `{study.command()}{only}`.\n\n",
            f"Not run (`--parts`): {', '.join(left_out)}; their columns are empty.\n\n" if left_out else "",
            f"{skipped[:1].upper()}{skipped[1:]}.\n\n" if skipped else "",
            S.markdown_table(table, columns + [("max_dt", "largest ok dt [s]")]),
            "\nResolution transfer (field_rel_l2, all, median):\n\n",
            S.markdown_table(res, [("method", "method")] + [(k, k) for k in grids])]
    return S.write_text_atomic(study.out / "summary.md", "".join(text))


def _parts_option(p) -> None:
    p.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS), metavar="PART",
                   help=f"the questions to ask, any of {', '.join(PARTS)} (default: all)")


def main(argv=None) -> None:
    study, args = S.parse_args("stability", __doc__, argv, extra=_parts_option)
    parts = tuple(p for p in PARTS if p in args.parts)
    evaluations(study, train_all(study), parts)
    csv_path = study.write_csv("stability.csv")
    study.finish([csv_path, plot(study, study.rows, parts), summary(study, study.rows, parts)])


if __name__ == "__main__":
    main()
