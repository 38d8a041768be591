"""What each results table of README.md and docs/ is made from (:data:`SPECS`, read by
:mod:`experiments.results_tables`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional


@dataclass(frozen=True)
class Spec:
    """Where a table's raw outputs appear and how the table is computed from them.

    kind:
        ``pareto``: ``pareto.csv`` of a Pareto study, the most accurate point of each method (as the study's own
        summary chooses it); ``study``: the ``table``-th Markdown table of the study's ``summary.md`` (the study's
        own reduction of its CSV, which is copied beside it); ``metrics``: rows ``metrics`` (label, key) of a
        run's ``metrics.json`` (or of the JSON file ``file``, nested keys joined by ``/``: e.g. ``results.json`` of
        ``experiments/scenes.py``); ``stack``: one row per table of ``parts`` (label, table name), the rows of
        each one's study CSV where column ``where[0]`` is ``where[1]``, cells ``columns`` (header, key, and
        optionally a factor the value is multiplied by: seconds → ms); its provenance is that of the parts; ``cells``: a
        table assembled from the cells of other tables (``results/<name>/cells.json``: a header and rows of text
        templates, see :func:`fill_cell`), with the provenance of the tables it quotes; ``transcribed``: no raw
        outputs known, ``table.csv`` only.
    raw: the folder of the raw outputs, relative to the repository (None: given on the command line, or none).
    command: the command that makes them.
    """

    kind: str
    command: str
    raw: Optional[str] = None
    table: int = 0
    csv: Optional[str] = None
    metrics: tuple[tuple[str, str], ...] = ()
    file: str = "metrics.json"
    parts: tuple[tuple[str, str], ...] = ()
    columns: tuple[tuple[Any, ...], ...] = ()  # (header, key) or (header, key, factor)
    where: tuple[str, str] = ("", "")


SCENES = ["pendulum", "double_pendulum", "bump", "elastic", "elastic_actuated", "soft_body"]


def _study(name: str, scene: str, kind: str = "study", table: int = 0) -> Spec:
    suffix = "" if scene == "pendulum" else f"-{scene}"
    flag = "" if scene == "pendulum" else f" --scene {scene}"
    return Spec(kind=kind, command=f"python -m experiments.{name}{flag}", raw=f"outputs/studies/{name}{suffix}",
                table=table, csv=f"{name}.csv")


PENDULUM_METRICS = (
    ("`field_rel_l2/all/median`", "field_rel_l2/all/median"),
    ("`field_rel_l2/in_horizon/median`", "field_rel_l2/in_horizon/median"),
    ("`field_rel_l2/extrapolation/median` (t ≥ 2.5 s)", "field_rel_l2/extrapolation/median"),
    ("`field_rel_l2/all/max`", "field_rel_l2/all/max"),
    ("`projection_rel_l2/all/median` (the embedding's own floor)", "projection_rel_l2/all/median"),
    ("`energy_rel_err/max` (m g ℓ units)", "energy_rel_err/max"),
    ("`energy_drift_long/max` (1 000 steps)", "energy_drift_long/max"),
    ("`vpt/median` [s]", "vpt/median"),
    ("`rollout_seconds_per_trajectory`", "rollout_seconds_per_trajectory"),
    ("data and training [s] · whole run [s]", "train_seconds|total_seconds"),
    ("epochs run (of the budget)", "epochs_run|max_epochs"),
)

# a scene's default run, in the scene's own energy unit (E_scale)
SCENE_METRICS = (
    ("`field_rel_l2/all/median` (the whole 5 s)", "field_rel_l2/all/median"),
    ("`field_rel_l2/in_horizon/median` · `/max`", "field_rel_l2/in_horizon/median|field_rel_l2/in_horizon/max"),
    ("`field_rel_l2/extrapolation/median` (after the training horizon)", "field_rel_l2/extrapolation/median"),
    ("`projection_rel_l2/all/median` (the embedding's own floor)", "projection_rel_l2/all/median"),
    ("`energy_rel_err/max` (E_scale units)", "energy_rel_err/max"),
    ("`energy_drift_long/max` (1 000 steps)", "energy_drift_long/max"),
    ("`vpt/median` [s]", "vpt/median"),
    ("`rollout_seconds_per_trajectory` · with decoding", "rollout_seconds_per_trajectory|fields_seconds_per_trajectory"),
    ("data and training [s] · whole run [s]", "train_seconds|total_seconds"),
    ("epochs run (of the budget)", "epochs_run|max_epochs"),
)

# a table of the reduced dynamics and the rollouts through it (lnf.evaluate's metrics)
TABLE_METRICS = (
    ("table: nodes built · terms read", "table_points|table_terms"),
    ("table: error against the exact pullback · build [s]", "table_error|table_seconds"),
    ("`field_rel_l2/in_horizon/median` · `/extrapolation/median`",
     "field_rel_l2/in_horizon/median|field_rel_l2/extrapolation/median"),
    ("`rollout_seconds_per_trajectory` · with decoding", "rollout_seconds_per_trajectory|fields_seconds_per_trajectory"),
)

# experiments/scenes.py's results.json on a body with an expensive reference (speedup) and an added damping (damped)
FEM_SCENE_MEASUREMENTS = (
    ("test trajectories · training horizon [s] · FEM state entries (u and v of every node, the load)",
     "trajectories|horizon_s|fom_state_size"),
    ("FEM: largest step tried (× its own) · its seconds for all of them", "fom_step_factor|fom_seconds"),
    ("ours, Chebyshev table: step [s] · seconds · speed-up", "rom_dt|rom_seconds|speedup"),
    ("ours, exact pullback: seconds · speed-up", "rom_seconds_exact|speedup_exact"),
    ("ours, table, every stored frame decoded on the evaluation points: points · seconds · speed-up",
     "decoding_points|rom_seconds_with_decoding|speedup_with_decoding"),
    ("conservative: `field_rel_l2` in horizon (median · max) · after it", "ours/field_rel_l2/in_horizon/median|"
     "ours/field_rel_l2/in_horizon/max|ours/field_rel_l2/extrapolation/median"),
    ("conservative: `energy_drift_long/max` (1 000 steps) · diverged long rollouts",
     "ours/energy_drift_long/max|ours/diverged_count_long"),
    ("damped (α [1/s], trained undamped): α · `field_rel_l2` all (median · max) · in horizon · after",
     "damped/damping_per_second|damped/field_rel_l2/all/median|damped/field_rel_l2/all/max|"
     "damped/field_rel_l2/in_horizon/median|damped/field_rel_l2/extrapolation/median"),
    ("damped: dissipated energy, ours / FEM (median) · largest energy error / E_scale · diverged fraction",
     "damped/dissipated_ratio_ours_over_reference_median|damped/energy_error_max_over_scale|"
     "damped/diverged_fraction"),
    ("all measurements [s]", "seconds"),
)

# experiments/scenes.py's results.json of a conservative scene with a black box (black_box) and POD-Galerkin (modes)
BLACK_BOX_MEASUREMENTS = (
    ("`vpt/median` [s]: ours · black box", "ours/vpt/median|black_box/vpt/median"),
    ("`field_rel_l2` all · in horizon (median): ours", "ours/field_rel_l2/all/median|ours/field_rel_l2/in_horizon/median"),
    ("`field_rel_l2` all · in horizon (median): black box",
     "black_box/field_rel_l2/all/median|black_box/field_rel_l2/in_horizon/median"),
    ("energy drift over 20× the horizon, median: ours · black box · ratio",
     "ours/energy_drift_long/median|black_box/energy_drift_long/median|drift_ratio_median"),
    ("the same, max: ours · black box", "ours/energy_drift_long/max|black_box/energy_drift_long/max"),
)
MODES_MEASUREMENTS = (
    ("POD-Galerkin modes to match ours · the best linear projection's", "pod_modes_to_match_ours|oracle_modes_to_match_ours"),
)
# experiments/scenes.py's results.json of a forced scene (loads, decay)
LOADS_MEASUREMENTS = (
    ("test loads: `field_rel_l2` in horizon · all · after (median)", "test/field_rel_l2/in_horizon/median|"
     "test/field_rel_l2/all/median|test/field_rel_l2/extrapolation/median"),
    ("a load not in training (amplitude, frequency [Hz])", "unseen_load/controls"),
    ("that load: `field_rel_l2` in horizon · all (median · max)", "unseen_load/field_rel_l2/in_horizon/median|"
     "unseen_load/field_rel_l2/all/median|unseen_load/field_rel_l2/all/max"),
    ("free decay: largest rise of the reduced energy between samples / E_scale",
     "free_decay/largest_energy_rise_per_sample_over_scale"),
    ("free decay: energy at the end over the start, ours · FEM (median)",
     "free_decay/energy_ratio_end_over_start_ours_median|free_decay/energy_ratio_end_over_start_fem_median"),
    ("all measurements [s]", "seconds"),
)

# python -m experiments.probe_settings --out probe.json: the embedding after a fixed number of steps
PROBE_METRICS = (
    ("projection error, 32×32 (training grid)", "projection_rel_l2_32"),
    ("projection error, 64×64 (test grid)", "projection_rel_l2_64"),
    ("projection error, 4 096 points uniform over the body", "projection_rel_l2_uniform"),
    ("rollout error, 64×64: GL32 · GL8 in the dynamics", "rollout_rel_l2_64_GL32|rollout_rel_l2_64_GL8"),
    ("boundary ring's share of the squared 64×64 error", "ring_share_of_sq_error"),
    ("ε = ‖J‖²/⟨J, u⟩² − 1, interior codes: min · max", "eps_interior_min|eps_interior_max"),
    ("training steps · seconds", "steps|train_seconds"),
)

SPECS: dict[str, Spec] = {
    **{f"pareto-{s}": _study("pareto", s, "pareto") for s in SCENES},
    **{f"stability-{s}": _study("stability", s) for s in SCENES},
    **{f"stability-{s}-resolution": _study("stability", s, table=1) for s in ("pendulum", "soft_body")},
    **{f"sparse_noisy-{s}": _study("sparse_noisy", s) for s in SCENES},
    **{f"model_size-{s}": _study("model_size", s) for s in ("pendulum", "elastic", "elastic_actuated", "soft_body")},
    # the same studies' second table: the baselines (POD-Galerkin, Operator Inference, the black box) at the question
    **{f"model_size-{s}-baselines": _study("model_size", s, table=1) for s in ("elastic", "elastic_actuated",
                                                                               "soft_body")},
    # issue 44 item 2: d = 3, 4 (the first table: lnf; the second: POD-Galerkin k = 3, 4 and OpInf), the three
    # elastic scenes' at the defaults of 2026-12-07 but the closure's shooting (then beyond a 2-core machine)
    **{f"model_size-{s}-d34{tail}": Spec(
        "study", f"python -m experiments.model_size --scene {s} --dims 3,4 --widths 64 --modes 3,4 "
        + "--set evaluation.closure_shooting_iterations=0 "
        + f"--out outputs/studies/model_size-{s}-d34", raw=f"outputs/studies/model_size-{s}-d34",
        table=table, csv="model_size.csv") for s in ("elastic", "elastic_actuated", "soft_body")
        for tail, table in (("", 0), ("-baselines", 1))},
    # the closure's shooting at d = 3 (degree lowered to 2 by model.closure_max_terms, 4 trajectories on the 32³
    # table) on the d = 3 checkpoints of the searches above: without and with the closure
    "closure_ablation-d3": Spec(
        "study", "python -m experiments.closure_ablation --ckpt <the d = 3 checkpoints of model_size-{elastic,"
        "elastic_actuated}-d34> --degree 4 --threads 1 --out outputs/studies/closure_ablation-d3",
        raw="outputs/studies/closure_ablation-d3", table=0, csv="closure.json"),
    # the same at d = 4 on the cantilever (degree 2, 14 terms, the 16⁴ table; a stage stops when it stalls)
    "closure_ablation-elastic-d4": Spec(
        "study", "python -m experiments.closure_ablation --ckpt <the d = 4 checkpoint of model_size-elastic-d34> "
        "--degree 4 --threads 1 --out outputs/studies/closure_ablation-elastic-d4",
        raw="outputs/studies/closure_ablation-elastic-d4", table=0, csv="closure.json"),
    "closure_ablation-elastic_actuated-d4": Spec(
        "study", "python -m experiments.closure_ablation --ckpt <the d = 4 checkpoint of model_size-elastic_actuated-d34> "
        "--degree 4 --threads 1 --out outputs/studies/closure_ablation-elastic_actuated-d4",
        raw="outputs/studies/closure_ablation-elastic_actuated-d4", table=0, csv="closure.json"),
    # the soft body at d = 3, 4 (tables refined per axis since 43afd1d: 128 × 16 × 16 nodes at d = 3, 128 × 8³ at d = 4)
    **{f"closure_ablation-soft_body-d{d}": Spec(
        "study", f"python -m experiments.closure_ablation --ckpt <the d = {d} checkpoint of model_size-soft_body-d34> "
        f"--degree 4 --threads 1 --out outputs/studies/closure_ablation-soft_body-d{d}",
        raw=f"outputs/studies/closure_ablation-soft_body-d{d}", table=0, csv="closure.json") for d in (3, 4)},
    # a checkpoint trained here (python -m lnf.train +experiment=<scene> <the reduced settings> model.latent_dim=<d>
    # model.closure_degree=0), then the closure ablation with the codes' spans floored (CODE_SPAN_FLOOR)
    **{f"closure_ablation-{s}-d{d}-floor": Spec(
        "study", f"python -m experiments.closure_ablation --ckpt <a {s} checkpoint at d = {d}, reduced settings> "
        f"--degree 4 --threads 1 --out outputs/studies/closure_ablation-{s}-d{d}-floor",
        raw=f"outputs/studies/closure_ablation-{s}-d{d}-floor", table=0, csv="closure.json")
       for s, d in (("soft_body", 3), ("soft_body", 4), ("elastic", 3), ("elastic_actuated", 3), ("elastic", 4))},
    **{f"seeds-{s}": _study("seeds", s) for s in SCENES},
    "cost_scaling-pendulum": _study("cost_scaling", "pendulum"),
    **{f"roofline-{s}": _study("roofline", s) for s in SCENES},
    "roofline-defaults": Spec("stack", "python -m experiments.roofline --scene <scene>",
                              parts=tuple((s.replace("_", " "), f"roofline-{s}") for s in SCENES),
                              where=("default", "True"), columns=(
        ("SIREN width", "width"), ("trajectories", "batch"), ("quadrature points", "points"),
        ("FLOPs per step", "flops"), ("ms per RK4 step", "seconds", 1e3), ("× the bound", "ratio"),
        ("matmul peak, same run [GFLOP/s]", "matmul_peak_gflops"))),
    "summary": Spec("cells", "python -m experiments.results_tables"),
    "pendulum_default": Spec("metrics", "python -m lnf.train +experiment=pendulum", metrics=PENDULUM_METRICS),
    "pendulum_acceptance": Spec("metrics", "python -m experiments.pendulum_acceptance", file="acceptance.json", metrics=(
        ("wall-clock of the train command [s] (data generation, training, test evaluation; target ≤ 1 200)",
         "train_wall_seconds"),
        ("`field_rel_l2/all/median` (target ≤ 0.02)", "field_rel_l2/all/median"),
        ("`field_rel_l2/extrapolation/median`, t ≥ 2.5 s (target ≤ 0.03)", "field_rel_l2/extrapolation/median"),
        ("`field_rel_l2/in_horizon/median` · `field_rel_l2/all/max`", "field_rel_l2/in_horizon/median|field_rel_l2/all/max"),
        ("`projection_rel_l2/all/median` (the embedding's own floor)", "projection_rel_l2/all/median"),
        ("`energy_rel_err/max` (m g ℓ units, 100-sample rollout; target ≤ 0.02)", "energy_rel_err/max"),
        ("`energy_drift_long/max` over 10 000 steps of 4 test trajectories (dt = 0.05 s, 200× the training horizon; "
         "target ≤ 1e-3)", "energy_drift_long/max"),
        ("`vpt/median` [s]", "vpt/median"),
        ("`rollout_seconds_per_trajectory` (100 steps, 16 trajectories at once)", "rollout_seconds_per_trajectory"),
        ("epochs run (of the budget)", "epochs_run|max_epochs"),
        ("every target met", "passed"),
    )),
    "soft_body_default": Spec("metrics", "python -m lnf.train +experiment=soft_body", metrics=SCENE_METRICS),
    "elastic_default": Spec("metrics", "python -m lnf.train +experiment=elastic", metrics=SCENE_METRICS),
    # the elastic scenes' defaults at d = 2 (issue 44 item 3: the state dimension of Operator Inference at r = 4)
    **{f"{scene}_d2_default": Spec("metrics", f"python -m lnf.train +experiment={scene} model.latent_dim=2",
                                   metrics=SCENE_METRICS) for scene in ("elastic", "elastic_actuated", "soft_body")},
    # the cantilever's default at another SIREN frequency, quoted beside elastic_default (docs/choices.md)
    "elastic-w0-3": Spec("metrics", "python -m lnf.train +experiment=elastic model.w0=3", metrics=SCENE_METRICS),
    "elastic-w0": Spec("cells", "python -m experiments.results_tables"),
    "elastic_scenes": Spec("metrics", "python -m experiments.scenes --scene elastic --measure speedup",
                           metrics=FEM_SCENE_MEASUREMENTS[:-1], file="results.json"),
    "double_pendulum_default": Spec("metrics", "python -m lnf.train +experiment=double_pendulum", metrics=SCENE_METRICS),
    "bump_default": Spec("metrics", "python -m lnf.train +experiment=bump", metrics=SCENE_METRICS),
    "double_pendulum_scenes": Spec("metrics", "python -m experiments.scenes --scene double_pendulum",
                                   metrics=BLACK_BOX_MEASUREMENTS + MODES_MEASUREMENTS, file="results.json"),
    "bump_scenes": Spec("metrics", "python -m experiments.scenes --scene bump",
                        metrics=BLACK_BOX_MEASUREMENTS + MODES_MEASUREMENTS, file="results.json"),
    "elastic_actuated_scenes": Spec("metrics", "python -m experiments.scenes --scene elastic_actuated --measure loads decay "
                                    "--unseen-load 0.5 1.2", metrics=LOADS_MEASUREMENTS, file="results.json"),
    "elastic_actuated_default": Spec("metrics", "python -m lnf.train +experiment=elastic_actuated",
                                     metrics=SCENE_METRICS),
    "soft_body_scenes": Spec("metrics", "python -m experiments.scenes --scene soft_body --measure speedup shape damped",
                             metrics=FEM_SCENE_MEASUREMENTS, file="results.json"),
    **{f"pendulum_grid-{g}": Spec("metrics", f"python -m lnf.train +experiment=pendulum data.coarse_grid={g.split('-')[0]}",
                                  metrics=PENDULUM_METRICS) for g in ("centres", "vertices", "vertices-lr1e-3")},
    "pendulum_grid": Spec("cells", "python -m experiments.results_tables"),
    **{f"probe-w0-{w}": Spec("metrics", f"python -m experiments.probe_settings --steps 650 --hyper-depth 0 "
                                        f"--velocity-weight 0 --w0 {w} --out <folder>/probe.json",
                             metrics=PROBE_METRICS, file="probe.json") for w in (10, 30)},
    "probe-w0": Spec("cells", "python -m experiments.results_tables"),
    "bench_defaults-pendulum": Spec("study", "python -m experiments.bench_defaults --scenes pendulum --baseline 9310cca "
                                    "--out outputs/studies/bench_defaults-pendulum",
                                    raw="outputs/studies/bench_defaults-pendulum", csv="bench_defaults.json"),
    "bench_defaults-pendulum-vertices": Spec("study", "python -m experiments.bench_defaults --override data.coarse_grid=vertices "
                                         "--out outputs/studies/bench_defaults-vertices",
                                         raw="outputs/studies/bench_defaults-vertices", csv="bench_defaults.json"),
    "pendulum_lr1e-3": Spec("metrics", "python -m lnf.train +experiment=pendulum optimizer.lr=1e-3",
                            metrics=PENDULUM_METRICS),
    "evaluate_readme": Spec("metrics", "python -m lnf.evaluate ckpt_path=<the pendulum_lr1e-3 run>/checkpoints/last.ckpt "
                            "integrator=rk4 integrator.substeps=5 dt=0.05 horizon=20 grid.kind=uniform "
                            "grid.resolution=128 long_steps=10000 dynamics=tabulated", metrics=(
        ("evaluation points", "evaluation_points"),
        ("decoding table: nodes · error (of the largest field)", "decoding_table_nodes|decoding_table_error"),
        ("`field_rel_l2/all/median` · `/extrapolation/median`", "field_rel_l2/all/median|field_rel_l2/extrapolation/median"),
        ("rollout · rollout + decoding per trajectory [s]", "rollout_seconds_per_trajectory|fields_seconds_per_trajectory"),
        ("long-horizon check: steps · seconds", "energy_drift_long/steps|energy_drift_long/seconds"),
        ("`energy_drift_long/max`", "energy_drift_long/max"),
        ("rollouts, decoding and checks [s] (`evaluation_seconds`: without start-up, ground truth and figures)",
         "evaluation_seconds"),
    )),
    # the soft body's d = 3, 4 tables refined per axis (since 43afd1d), on the model-size search's checkpoints, no closure
    **{f"soft_body_d{d}_table": Spec("metrics", f"python -m lnf.evaluate ckpt_path=<the d = {d} checkpoint of "
                                     "model_size-soft_body-d34> figures=0 threads=1", metrics=TABLE_METRICS)
       for d in (3, 4)},
    "elastic-oracle": Spec("study", "python -m experiments.elastic_diagnostics --oracle --degree 1 2 3",
                           raw="outputs/elastic_diagnostics/oracle", csv="oracle.json"),
    "elastic-release": Spec("study", "python -m experiments.elastic_diagnostics --content",
                            raw="outputs/elastic_diagnostics/content", csv="content.json"),
    "streaming": Spec("study", "python -m experiments.streaming", raw="outputs/streaming", csv="results.json"),
    "bench_training": Spec("study", "python -m experiments.bench_training --baseline <commit>",
                           raw="outputs/studies/bench_training", csv="bench_training.json"),
    "bench_training-tabulated": Spec("study", "python -m experiments.bench_training --baseline <commit>",
                                     raw="outputs/studies/bench_training", csv="bench_training.json", table=1),
    # the worked example of docs/own_system.md, a scene kept outside the package
    **{f"{name}-vibrating_string": Spec(kind, f"PYTHONPATH=examples python -m experiments.{name} --config-dir examples/conf "
                                              f"--scene vibrating_string", raw=f"outputs/studies/{name}-vibrating_string",
                                        csv=f"{name}.csv")
       for name, kind in [("pareto", "pareto"), ("stability", "study")]},
}


def spec_of(name: str, provenance: dict[str, Any]) -> Spec:
    """The registered spec of a table, or a transcribed one made from its provenance."""
    if name in SPECS:
        return SPECS[name]
    return Spec("transcribed", provenance.get("command", ""))
