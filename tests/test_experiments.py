"""Smoke tests: the benchmark scripts in experiments/ run end to end with tiny settings."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _run(args, png_only=False):
    """`python args...` from the repository root; `png_only`: figures without their PDF (LNF_FIGURE_PDF=0), for
    tests that do not look at them."""
    env = {**os.environ, "LNF_FIGURE_PDF": "0"} if png_only else None
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=300, check=True,
                          env=env)


def test_bench_rollout_step_prints_a_ratio():
    out = _run(["-m", "experiments.bench_rollout_step", "--batch", "1", "2", "--width", "16", "--order", "3",
                "--repeats", "2", "--threads", "1"]).stdout
    rows = [line for line in out.splitlines() if line.strip().startswith(("1 ", "2 "))]
    assert len(rows) == 2 and all("×" in r for r in rows)


def test_bench_table_prints_both_evaluations_and_their_ratio():
    out = _run(["-m", "experiments.bench_table", "--dims", "3", "--rows", "4"]).stdout
    (row,) = [line for line in out.splitlines() if line.startswith("d = 3")]
    assert "axis by axis" in row and "tensor basis" in row and float(row.split("ratio")[1]) > 0


def test_bench_training_measures_this_checkout_and_a_baseline_commit_in_the_same_run(tmp_path):
    """The training benchmark measures HEAD in a temporary git worktree beside this checkout (each in its own
    subprocess, importing its own lnf), counts the jets of a step from the code, and writes its table and raw
    numbers atomically; the worktree is removed afterwards."""
    import json

    out = tmp_path / "bench"
    _run(["-m", "experiments.bench_training", "--smoke", "--rounds", "1", "--threads", "1", "--baseline", "HEAD",
          "--out", str(out)])
    raw = json.loads((out / "bench_training.json").read_text())
    assert set(raw["rows"]) == {"this checkout", "baseline"}
    for row in raw["rows"].values():
        assert row["jets_per_step"] >= 3 and row["step_seconds"] > 0 and row["decode_seconds"] > 0
        assert row["step_flops"] > 0
    summary = (out / "summary.md").read_text()
    assert summary.startswith("Machine: ") and "Command: `python -m experiments.bench_training --smoke --baseline HEAD`" in summary
    assert "against the baseline: training step time ×" in summary
    table = raw["rows"]["this checkout"]  # this checkout decodes through a table too, and measures its error
    assert table["table_decode_seconds"] > 0 and table["table_nodes"] >= 16 and 0 <= table["table_error"] <= 1e-5
    assert "| this checkout | " in summary.split("Chebyshev table")[1]
    assert not [p for p in out.iterdir() if p.name.startswith(".")]
    _assert_worktree_removed(raw["baseline_worktree"])


def test_bench_defaults_trains_each_checkout_and_scores_it_on_scattered_points(tmp_path):
    """The whole-run benchmark trains the scene's default in this checkout and in HEAD (a temporary worktree, with
    its own configs), evaluates each checkpoint on scattered points, and writes one table with the ratios."""
    out = tmp_path / "bench"
    _run(["-m", "experiments.bench_defaults", "--smoke", "--threads", "1", "--baseline", "HEAD", "--points", "64",
          "--out", str(out)])
    raw = json.loads((out / "bench_defaults.json").read_text())
    rows = raw["rows"]
    assert [r["checkout"] for r in rows] == ["baseline", "this checkout"]
    for r in rows:
        assert r["wall_seconds"] > 0 and r["epochs_run"] == r["max_epochs"] == 1 and r["points"] == 64
        assert r["grid"] > 0 and r["scattered"] > 0
        assert (out / f"pendulum-{r['checkout']}" / "scattered" / "metrics.json").is_file()
    summary = (out / "summary.md").read_text()
    assert "Command: `python -m experiments.bench_defaults --scenes pendulum --baseline HEAD --smoke`" in summary
    assert "This checkout against the baseline: pendulum: whole run ×" in summary
    _assert_worktree_removed(raw["baseline_worktree"])


def _assert_worktree_removed(path: str) -> None:
    """The benchmark's own baseline worktree is gone from disk and from git's list. Only its own: another
    benchmark test may hold a worktree of its own at the same moment on the other xdist worker."""
    assert path and "lnf-bench-" in path
    worktrees = subprocess.run(["git", "-C", str(ROOT), "worktree", "list", "--porcelain"], capture_output=True,
                               text=True).stdout
    listed = {line.split(" ", 1)[1] for line in worktrees.splitlines() if line.startswith("worktree ")}
    assert path not in listed and not Path(path).exists()


def test_probe_settings_reports_json():
    out = _run(["-m", "experiments.probe_settings", "--steps", "3", "--train", "2", "--test", "1", "--width", "16",
                "--threads", "1"]).stdout
    report = json.loads(out)
    assert report["steps"] == 3
    # 3 steps train nothing: a test rollout may diverge; it is counted, and the ring share is of the finite ones
    assert report["diverged_test_trajectories"] in (0, 1)
    if report["diverged_test_trajectories"] == 0:
        assert 0 <= report["ring_share_of_sq_error"] <= 1
    assert report["projection_rel_l2_uniform"] > 0  # the embedding scored on points over the whole body
    assert len(report["eps_along_codes"]) == 7


# ---------------------------------------------------------------------------------------------------
# the benchmark studies, each with --smoke settings. Every test has its own folder (data included): a test
# that reuses a study's output runs that study itself, so no result depends on the order or the worker
# that pytest-xdist gives the tests.
# ---------------------------------------------------------------------------------------------------
@pytest.fixture
def studies(tmp_path):
    return tmp_path


def _study(name, folder, *extra, tag=""):
    import os

    env = {**os.environ, "LNF_DATA_DIR": str(folder / "data"), "LNF_FIGURE_PDF": "1"}  # _assert_figure wants the PDF
    out = folder / f"{name}-smoke{tag}"
    proc = subprocess.run([sys.executable, "-m", f"experiments.{name}", "--smoke", "--threads", "1", "--out", str(out),
                           *extra], cwd=ROOT, capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return out, proc.stdout


def _assert_figure(out, name):
    """A study figure: the PNG and, beside it, its vector PDF; no temporary file left in the folder."""
    png, pdf = out / f"{name}.png", out / f"{name}.pdf"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and pdf.read_bytes()[:4] == b"%PDF", sorted(out.iterdir())
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name]


def _csv(path):
    import csv

    with open(path) as fh:
        return list(csv.DictReader(fh))


def _methods(rows):
    from experiments import studylib

    return {studylib.method_of(r) for r in rows}


def test_pareto_study_smoke(studies):
    out, stdout = _study("pareto", studies)
    rows = _csv(out / "pareto.csv")
    assert _methods(rows) == {"lnf", "lnf_closure", "latent_mlp", "pod", "full_order", "opinf", "opinf_observed"}
    assert {r["knob"] for r in rows} >= {"width", "k", "resolution", "quadrature", "integrator", "tabulated", "r"}
    closed = [r for r in rows if r["method"] == "lnf_closure"]  # the first width, its closure fitted by lnf.evaluate
    assert len(closed) == 1 and float(closed[0]["closure_val_error"]) <= float(closed[0]["closure_pullback_val_error"])
    opinf = [r for r in rows if r["method"] == "opinf"]
    assert [(r["model.latent_dim"], r["rank"]) for r in opinf] == [("1", "2"), ("2", "4")]  # r = 2d: q̃ and q̃̇
    assert all(float(r["cost_seconds"]) > 0 and float(r["train_seconds"]) > 0 for r in opinf)
    tabulated = [r for r in rows if r["knob"] == "tabulated"]
    assert all(float(r["table_nodes"]) >= 16 and float(r["table_fallback_fraction"]) >= 0 for r in tabulated)
    for name in ("pareto.png", "quadrature.png", "summary.md"):
        assert (out / name).stat().st_size > 0
    _assert_figure(out, "pareto")
    _assert_figure(out, "quadrature")
    summary = (out / "summary.md").read_text()
    assert "Black-box points dominated" in summary and "latent rollout cost" in summary
    assert "Against Operator Inference" in summary and "Operator Inference (full states)" in summary
    # its training jobs skip the long-horizon energy check, which no chart or table of the study reads
    trained = [r for r in rows if r["method"] in ("lnf", "latent_mlp", "pod") and r["knob"] in ("width", "k")]
    assert trained and not any(r.get("energy_drift_long/max") for r in trained)
    # rerunning reuses every finished sweep instead of training again
    _, again = _study("pareto", studies)
    assert "reusing" in again and "done in" not in again


def test_stability_study_smoke_then_cost_scaling_reuses_its_models(studies):
    """One test, one folder: the cost-scaling study reuses the models the stability study trained just before
    (as two tests sharing a module-scoped folder it depended on how pytest-xdist scheduled them)."""
    out, _ = _study("stability", studies)
    rows = _csv(out / "stability.csv")
    assert _methods(rows) == {"lnf", "latent_mlp", "pod", "full_order"}
    assert {r["study"] for r in rows} >= {"long", "high_energy", "dt", "resolution"}
    # the black box has no Hamiltonian: it is only integrated with RK4
    assert {r["integrator_name"] for r in rows if r.get("method") == "latent_mlp" and r["study"] != "train"} == {"rk4"}
    assert (out / "stability.png").stat().st_size > 0 and "largest ok dt" in (out / "summary.md").read_text()
    _assert_figure(out, "stability")

    out, stdout = _study("cost_scaling", studies)
    assert "reusing" in stdout
    rows = _csv(out / "cost_scaling.csv")
    assert _methods(rows) == {"lnf", "latent_mlp", "pod", "full_order"}
    assert {r["sweep"] for r in rows} == {"points", "batch"}
    assert all(float(r["rollout_seconds"]) > 0 and float(r["decode_peak_mib"]) >= 0 for r in rows)
    _assert_figure(out, "cost_scaling")


def test_sparse_noisy_study_smoke(studies):
    out, _ = _study("sparse_noisy", studies)
    rows = _csv(out / "sparse_noisy.csv")
    assert _methods(rows) == {"lnf", "latent_mlp", "pod", "full_order"}
    assert {r["data.observed_fraction"] for r in rows if r.get("knob") == "fraction"} == {"0.5", "0.25"}
    assert (out / "sparse_noisy.png").stat().st_size > 0
    _assert_figure(out, "sparse_noisy")


def test_model_size_study_smoke(studies):
    out, stdout = _study("model_size", studies)
    rows = _csv(out / "model_size.csv")
    ours = [r for r in rows if r["method"] == "lnf"]
    assert {(r["model.latent_dim"], r["model.width"]) for r in ours} == {("1", "8"), ("1", "16"), ("2", "8"), ("2", "16")}
    assert _methods(rows) == {"lnf", "latent_mlp", "pod", "full_order", "opinf", "opinf_observed"}
    assert "Operator Inference" in (out / "summary.md").read_text()
    assert "choice: d = 1" in stdout  # the smoke target (10) is met at d = 1 (a 1-epoch width-8 model may miss it)
    _assert_figure(out, "model_size")


def test_model_size_plot_draws_diverged_runs(tmp_path, monkeypatch):
    """A sweep where every run diverged (inf error, as a 1-epoch elastic model does) is charted, not a crash."""
    monkeypatch.setenv("LNF_FIGURE_PDF", "1")  # _assert_figure checks the PDF too
    from experiments import studylib
    from experiments.model_size import ERR, plot

    study = studylib.Study(name="model_size", scene="elastic", mode="smoke", out=tmp_path, threads=1)
    rows = [{"model.latent_dim": d, "model.width": w, ERR: float("inf")} for d in (1, 2) for w in (8, 16)]
    others = [{"method": "pod", "model.latent_dim": 1, ERR: 0.5}, {"method": "pod", "model.latent_dim": 2, ERR: float("inf")}]
    assert plot(study, rows, others, 0.1, None).stat().st_size > 0
    _assert_figure(tmp_path, "model_size")


def test_sparse_noisy_plot_legends_only_what_it_draws(tmp_path, monkeypatch):
    """A method the scene cannot run gets no legend entry; a diverged full-order reference gets no line at
    infinity but says "diverged" in the legend (the bump: the nodal model does not keep its shape)."""
    monkeypatch.setenv("LNF_FIGURE_PDF", "1")  # _assert_figure checks the PDF too
    import matplotlib.axes
    from experiments import studylib
    from experiments.sparse_noisy import ERR, plot

    legends = []
    draw = matplotlib.axes.Axes.legend
    monkeypatch.setattr(matplotlib.axes.Axes, "legend", lambda ax, *a, **k: legends.append(
        [t for t in ax.get_legend_handles_labels()[1]]) or draw(ax, *a, **k))
    study = studylib.Study(name="sparse_noisy", scene="elastic_actuated", mode="smoke", out=tmp_path, threads=1)
    rows = [{"method": m, "knob": "fraction", "data.observed_fraction": f, ERR: e, "diverged_fraction": 0}
            for m in ("lnf", "pod") for f, e in [(0.25, 0.1), (0.05, float("inf"))]]
    rows += [{"method": "lnf", "knob": "noise", "data.observed_fraction": 0.25, "data.noise": 0.1, ERR: 0.12},
             {"method": "full_order", "knob": "reference", ERR: float("inf"), "diverged_fraction": 1}]
    assert plot(study, rows).stat().st_size > 0
    _assert_figure(tmp_path, "sparse_noisy")
    assert len(legends) == 2
    for labels in legends:
        assert studylib.LABELS["latent_mlp"] not in labels and studylib.LABELS["lnf"] in labels
        assert "full order (no training data): diverged" in labels


def test_roofline_study_smoke(studies):
    out, stdout = _study("roofline", studies)
    rows = _csv(out / "roofline.csv")
    assert len(rows) == 7 and all(float(r["ratio"]) > 0 for r in rows)
    assert _methods(rows) == {"lnf", "latent_mlp", "pod", "full_order"}
    assert (out / "roofline.png").stat().st_size > 0
    _assert_figure(out, "roofline")


def test_roofline_study_on_the_double_pendulum_and_the_elastic_scene(studies):
    """The double pendulum's steps carry d = 2 (its FLOPs grow with the jet), POD is left out (its count is for
    d = 1); the elastic scene's steps also carry the ∇_X φ jets of its strain energy on its 12×6 rule."""
    out, _ = _study("roofline", studies, "--scene", "double_pendulum", tag="-double_pendulum")
    rows = _csv(out / "roofline.csv")
    assert _methods(rows) == {"lnf", "latent_mlp"}
    summary = (out / "summary.md").read_text()
    assert "double_pendulum, d = 2" in summary and "--scene double_pendulum" in summary
    from experiments.roofline import step_flops

    # the same width, batch and points: a d = 2 jet has more streams than a d = 1 one
    ours = [r for r in rows if r["method"] == "lnf"]
    assert ours and all(float(r["flops"]) > step_flops(int(r["batch"]), int(r["points"]), int(r["width"]), 2, 1, 2, 1)
                        for r in ours)

    out, _ = _study("roofline", studies, "--scene", "elastic", tag="-elastic")
    rows = _csv(out / "roofline.csv")
    assert _methods(rows) == {"lnf", "latent_mlp"}  # no nodal model of a mesh; POD's count is a scalar field's
    summary = (out / "summary.md").read_text()
    assert "elastic, d = 1" in summary and "--scene elastic" in summary
    for r in (r for r in rows if r["method"] == "lnf"):
        w, b, n = int(r["width"]), int(r["batch"]), int(r["points"])
        assert n == 12 * 6
        assert float(r["flops"]) == step_flops(b, n, w, 2, 1, 2, 2, spatial=True) > step_flops(b, n, w, 2, 1, 2, 2)


@pytest.mark.parametrize("experiment", ["pendulum", "double_pendulum", "elastic"])
def test_roofline_flop_model_matches_torch_flop_counter(experiment, tmp_path):
    """roofline.step_flops is the matmul count of ModulatedSiren.jet's streams: torch's own FlopCounterMode, run on
    one acceleration of the exact pullback, counts the same within the small contractions the model leaves out."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    from lnf.model import LagrangianNeuralField
    from lnf.quadrature import GaussLegendre

    from experiments import studylib
    from experiments.roofline import scene_of, step_flops

    study = studylib.Study(name="roofline", scene=experiment, mode="smoke", out=tmp_path, threads=1)
    scene, d, order, _, clamp, spatial = scene_of(study)  # as roofline.py --scene <experiment> builds it
    assert spatial == (experiment == "elastic")
    width, batch = 64, 8
    model = LagrangianNeuralField(scene, latent_dim=d, width=width, quadrature=GaussLegendre(order), clamp=clamp).eval()
    dyn = model.dynamics()
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        dyn.acceleration(0.1 * torch.randn(batch, d), torch.randn(batch, d))
    counted = counter.get_total_flops()
    modelled = step_flops(batch, len(dyn.points), width, 2, d, scene.body_dim, scene.field_dim, spatial) / 4
    assert modelled <= counted <= 1.1 * modelled, (counted, modelled)


def test_pareto_study_smoke_on_the_elastic_scene(studies):
    """A scene that trains with the tabulated pullback: the exact one is its variant, no nodal full-order model,
    and the FEM's own cost per trajectory is measured, drawn and compared."""
    out, _ = _study("pareto", studies, "--scene", "elastic", tag="-elastic")
    rows = _csv(out / "pareto.csv")
    assert _methods(rows) == {"lnf", "lnf_closure", "latent_mlp", "pod", "opinf", "opinf_observed"}
    assert any(r["knob"] == "exact" and r["dynamics"] == "lagrangian" for r in rows)
    assert not any(r["knob"] == "tabulated" for r in rows)
    simulator = json.loads((out / "simulator.json").read_text())
    assert simulator["simulator_seconds_per_trajectory"] > 0 and simulator["trajectories"] == 2
    assert "full-order simulator" in (out / "summary.md").read_text() and (out / "pareto.png").stat().st_size > 0


def test_stability_study_smoke_on_the_actuated_scene(studies):
    """Methods the scene cannot run are left out; its high-energy releases go to lnf.evaluate as .npy files (that part
    alone: `--parts`; the test above runs them all)."""
    out, _ = _study("stability", studies, "--scene", "elastic_actuated", "--parts", "high_energy", tag="-actuated")
    rows = _csv(out / "stability.csv")
    assert _methods(rows) == {"lnf", "pod"}
    assert {r["study"] for r in rows} == {"train", "high_energy"}  # only the part asked for
    summary = (out / "summary.md").read_text()
    assert "Not run (`--parts`): long, dt, resolution" in summary
    # damped and loaded: its energy changes by the forces' work, so the table gives the error against the FEM's
    assert "energy error vs the reference 20×" in summary and "energy drift" not in summary
    energy = [r for r in rows if r.get("study") == "high_energy"]
    assert sorted({float(r["stress_level"]) for r in energy}) == [0.15, 0.2]
    assert all(Path(r["initial_states"]).suffix == ".npy" for r in energy)
    assert (out / "stability.png").stat().st_size > 0


# ---------------------------------------------------------------------------------------------------
# a scene of your own (docs/own_system.md, "Benchmark studies on your scene"): the worked example of examples/,
# its module on PYTHONPATH and its config folder given with --config-dir, with no change to lnf/ or experiments/
# ---------------------------------------------------------------------------------------------------
EXAMPLES = ROOT / "examples"


def test_a_study_takes_a_config_dir_and_the_relative_paths_of_the_folder_it_is_run_from(tmp_path, monkeypatch,
                                                                                          capsys):
    from experiments import studylib as S

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PYTHONPATH", os.path.relpath(EXAMPLES, tmp_path))
    monkeypatch.setenv("LNF_DATA_DIR", "data")
    study, _ = S.parse_args("pareto", "", ["--config-dir", os.path.relpath(EXAMPLES / "conf", tmp_path),
                                           "--scene", "vibrating_string", "--smoke", "--out", "out"])
    assert study.config_dir == EXAMPLES / "conf" and study.out == (tmp_path / "out").resolve()
    assert study.scene_object().body_dim == 1 and not study.supports("full_order")
    assert study.command() == ("PYTHONPATH=examples python -m experiments.pareto --smoke --config-dir examples/conf "
                               "--scene vibrating_string")  # reruns it from the repository root
    env = S.job_environment()  # the jobs run in the repository root: the caller's relative paths made absolute
    assert env["PYTHONPATH"] == str(EXAMPLES) and env["LNF_DATA_DIR"] == str((tmp_path / "data").resolve())
    assert S.config_file("model/pod", study.config_dir) == ROOT / "conf" / "model" / "pod.yaml"

    with pytest.raises(SystemExit):
        S.parse_args("pareto", "", ["--config-dir", str(EXAMPLES / "conf"), "--scene", "nowhere"])
    err = capsys.readouterr().err
    assert str(ROOT / "conf" / "experiment" / "nowhere.yaml") in err
    assert str(EXAMPLES / "conf" / "experiment" / "nowhere.yaml") in err
    with pytest.raises(SystemExit):  # a scene of your own without its config folder
        S.parse_args("pareto", "", ["--scene", "vibrating_string"])
    assert "--config-dir" in capsys.readouterr().err


def test_a_study_adds_the_users_overrides_to_every_training_job_and_to_its_command(capsys):
    """--set KEY=VALUE (repeatable) comes after the study's own settings, so it wins over them (not over the
    study's sweep); the summaries' command reruns it; anything but KEY=VALUE is refused by name."""
    from experiments import studylib as S

    study, _ = S.parse_args("model_size", "", ["--scene", "elastic", "--set", "evaluation.closure_shooting_iterations=0",
                                               "--set", "trainer.max_epochs=30"])
    ours = study.method("lnf", ["model.latent_dim=1,2"])
    assert ours[-3:] == ["evaluation.closure_shooting_iterations=0", "trainer.max_epochs=30", "model.latent_dim=1,2"]
    assert "trainer.max_epochs=15" in ours  # the reduced settings', overridden by the user's after it
    assert study.method("pod")[-2:] == ["evaluation.closure_shooting_iterations=0", "trainer.max_epochs=30"]
    assert study.command() == ("python -m experiments.model_size --set evaluation.closure_shooting_iterations=0 "
                               "--set trainer.max_epochs=30 --scene elastic")
    for bad in ("model.w0", "=3"):
        with pytest.raises(SystemExit):
            S.parse_args("model_size", "", ["--set", bad])
        assert f"--set {bad!r}: expected a Hydra override KEY=VALUE" in capsys.readouterr().err


def test_pareto_and_scenes_run_the_vibrating_string_from_its_own_folder(tmp_path):
    """Started from a folder that is not the repository, as a user would: the repository root (which holds the
    studies' package) and, relative, the example's module on PYTHONPATH, a relative data dir (LNF_DATA_DIR) and relative output folders, which the studies' jobs (run in the
    repository root) must see as the caller meant them; the config folder relative for the study, absolute for
    scenes.py. The string is a 1-D body: no nodal full-order model."""
    work = tmp_path / "work"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.path.relpath(EXAMPLES, work)]),
           "LNF_DATA_DIR": "data", "WANDB_MODE": "offline"}

    def run(study: str, *args: str) -> str:
        proc = subprocess.run([sys.executable, "-m", f"experiments.{study}", *args], cwd=work, env=env,
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        return proc.stdout

    scene = ["--scene", "vibrating_string", "--smoke", "--threads", "1"]
    stdout = run("pareto", "--config-dir", os.path.relpath(EXAMPLES / "conf", work), *scene, "--out", "pareto")
    out = (work / "pareto").resolve()
    rows = _csv(out / "pareto.csv")
    assert _methods(rows) == {"lnf", "lnf_closure", "latent_mlp", "pod", "opinf", "opinf_observed"}  # no full-order model in 1-D
    assert "full order left out" in stdout
    assert {r["knob"] for r in rows} >= {"width", "k", "quadrature", "integrator", "tabulated"}
    assert all(r["dir"].startswith(str(out)) for r in rows)  # the relative --out, as the caller meant it
    assert list((work / "data").glob("vibratingstring-*.h5"))  # the relative LNF_DATA_DIR, too
    summary = (out / "summary.md").read_text()
    assert "Left out, as the scene's baselines() says they cannot run it: full order" in summary
    assert "--config-dir examples/conf --scene vibrating_string" in summary and "PYTHONPATH=examples" in summary
    assert (out / "pareto.png").stat().st_size > 0 and (out / "quadrature.png").stat().st_size > 0

    # the acceptance measurements the string's declarations allow, on the Pareto study's width-16 model
    run("scenes", "--config-dir", str(EXAMPLES / "conf"), "--scene", "vibrating_string", "--ckpt",
        "pareto/lnf_width/0/checkpoints/last.ckpt", "--out", "scenes", "--max-modes", "2", "--bb-iterations", "10",
        "--threads", "1")
    result = json.loads((work / "scenes" / "results.json").read_text())
    assert result["measurements"] == ["black_box", "modes"]
    assert set(result["skipped"]) == {"speedup", "loads", "decay", "shape", "damped"} and len(result["pod"]) == 2
    assert (work / "scenes" / "vpt.png").is_file() and (work / "scenes" / "modes.png").is_file()


def test_stability_on_the_vibrating_string_skips_its_high_energy_part_and_says_why():
    """The string defines released_at_rest() but no stability_cases(): the stability study has no high-energy part
    (the other questions run as on any scene, see test_stability_study_smoke_*) and says what would add one; its
    resolution transfer is labelled in points of a 1-D grid."""
    from experiments import stability
    from experiments import studylib as S

    study, _ = S.parse_args("stability", "", ["--config-dir", str(EXAMPLES / "conf"), "--scene", "vibrating_string",
                                              "--smoke"])
    assert stability.stress_cases(study) is None
    note = stability.skipped_high_energy(study)
    assert "defines released_at_rest() but no stability_cases()" in note and "StabilityCases" in note
    assert stability.grid_name({"grid.kind": "uniform", "grid.resolution": "8"}, 1) == "8 points"


def test_stability_resolution_transfer_keeps_a_3d_body_in_memory():
    from experiments import stability

    assert stability.transfer_resolutions(2) == "16,64,128" and stability.transfer_resolutions(1) == "16,64,128"
    assert max(int(r) for r in stability.transfer_resolutions(3).split(",")) ** 3 <= 32 ** 3
    assert stability.transfer_resolutions(3, smoke=True) == "8"


def test_stability_high_energy_states_per_scene():
    import numpy as np

    from experiments import stability, studylib
    from lnf.scenes import LiftedDoublePendulum, LiftedPendulum

    study = type("Study", (), {"out": Path("/nonexistent")})()  # inline states write no file
    for scene, size in [(LiftedPendulum(), 2), (LiftedDoublePendulum(), 4)]:
        cases = scene.stability_cases()
        args = stability.initial_state_arguments(study, scene, cases, cases.levels)
        assert list(args.values()) == list(cases.levels)
        for arg, level in args.items():
            state = json.loads(arg)
            expected = [level * np.pi, 0.0] if size == 2 else [level * np.pi, level * np.pi, 0.0, 0.0]
            assert np.allclose(state[0], expected, atol=1e-6) and stability._state_key(state) == arg  # the row finds its level again
    for path in (ROOT / "conf" / "experiment").glob("*.yaml"):  # every built-in experiment's scene has release cases
        study = studylib.Study(name="stability", scene=path.stem, mode="smoke", out=Path("/nonexistent"), threads=1)
        assert stability.stress_cases(study) is not None, path.stem


def test_pareto_mask_and_study_choices():
    import numpy as np

    from experiments import studylib
    from experiments.model_size import choose
    from experiments.stability import failure_dt

    mask = studylib.pareto_mask(np.array([1, 2, 3, 4, np.nan]), np.array([5, 3, 4, 1, 0]))
    assert mask.tolist() == [True, True, False, True, False]
    assert studylib.dominates(np.array([1.0, 2.0]), np.array([0.5, 0.1]), 2.0, 0.2)
    assert not studylib.dominates(np.array([1.0, 2.0]), np.array([0.5, 0.1]), 1.5, 0.2)
    rows = [{"dt": 0.05, "field_rel_l2/all/median": 0.01}, {"dt": 0.1, "field_rel_l2/all/median": 0.04},
            {"dt": 0.2, "field_rel_l2/all/median": 0.06}, {"dt": 0.4, "field_rel_l2/all/median": 0.01,
                                                         "diverged_fraction": 0.5}]
    assert failure_dt(rows) == 0.1  # 0.06 > max(2 × 0.01, 0.05)
    runs = [{"model.latent_dim": d, "model.width": w, "field_rel_l2/all/median": e}
            for d, w, e in [(1, 16, 0.3), (1, 32, 0.08), (1, 64, 0.05), (2, 16, 0.09), (2, 32, 0.04)]]
    assert choose(runs, 0.1) == runs[1] and choose(runs, 0.045) == runs[4] and choose(runs, 0.01) is None


def test_scenes_script_measures_a_tiny_double_pendulum_checkpoint(tmp_path):
    """The black box and vpt of a d = 2 scene (the POD modes of a 1-D body: the vibrating string's test above)."""
    run = tmp_path / "run"
    data = ["data.n_train=3", "data.n_val=1", "data.n_test=2", "data.n_times=20", "data.train_times=10",
            "data.fine_resolution=12", "data.coarse_resolution=8", "model.width=16", "model.hyper_width=8",
            "quadrature.order=4", "evaluation.long_steps=10", "evaluation.long_trajectories=1",
            "evaluation.max_reduction_points=64", f"paths.data_dir={tmp_path / 'data'}",
            "evaluation.figures=0"]  # the script's figures are checked, not the run's
    _run(["-m", "lnf.train", "+experiment=double_pendulum", "trainer=smoke", "logger=csv", *data,
          f"hydra.run.dir={run}"], png_only=True)
    _run(["-m", "experiments.scenes", "--scene", "double_pendulum", "--ckpt", str(run / "checkpoints" / "last.ckpt"),
          "--out", str(tmp_path / "out"), "--max-modes", "2", "--bb-iterations", "10", "--threads", "1",
          "--measure", "black_box"], png_only=True)
    result = json.loads((tmp_path / "out" / "results.json").read_text())
    assert result["measurements"] == ["black_box"]
    assert {"ours", "black_box", "drift_ratio_median"} <= set(result) and (tmp_path / "out" / "vpt.png").is_file()
    assert result["integrator"] == {"name": "implicit_midpoint", "order": 2}  # the experiment's, as lnf.train's


def test_scenes_script_chooses_its_measurements_by_what_the_scene_declares():
    """No scene names: the black box where baselines() allows it, POD modes where POD can run, the speed-up where the
    reference is expensive, loads where the scene has controls, the free decay where it is not conservative, the
    damped rollout where a conservative scene can add a damping."""
    import numpy as np

    from experiments import scenes
    from vibrating_string import VibratingString

    from lnf.scenes import ElasticCantilever, LiftedDoublePendulum

    def allowed(scene):
        return [m for m, why in scenes.applicable(scene).items() if why is None]

    assert allowed(LiftedDoublePendulum()) == allowed(VibratingString()) == ["black_box", "modes"]
    assert allowed(ElasticCantilever(mesh=(6, 3))) == ["black_box", "modes", "speedup", "damped"]
    actuated = ElasticCantilever(mesh=(6, 3), damping=0.3, load_amplitude_range=(-0.6, 0.6),
                                 load_frequency_range=(0.3, 0.7))
    assert allowed(actuated) == ["modes", "speedup", "loads", "decay"]
    assert "baselines()" in scenes.applicable(actuated)["black_box"]
    assert "not conservative" in scenes.applicable(actuated)["damped"]
    assert "with_damping" in scenes.applicable(VibratingString())["damped"]
    # loads are set where the scene keeps them (the state's last entries), checked through controls()
    states = actuated.sample_initial_states(3, np.random.default_rng(0))
    moved = scenes.with_controls(actuated, states, np.tile([0.5, 1.2], (3, 1)))
    assert np.array_equal(actuated.controls(moved), np.tile([0.5, 1.2], (3, 1)))
    assert np.array_equal(moved[:, :-2], states[:, :-2])
    training = actuated.controls(states)
    assert np.all(scenes.unseen_load(training, None) > training.max(0))  # beyond the training range
    assert scenes.unseen_load(training, [0.5, 1.2]).tolist() == [0.5, 1.2]


@pytest.mark.parametrize("scene", ["elastic", "elastic_actuated"])
def test_scenes_script_measures_a_tiny_elastic_checkpoint(scene, tmp_path):
    """The speed-up, step search and damped rollout (elastic), the decay and unseen load (actuated), and the tip
    figures."""
    run = tmp_path / "run"
    _run(["-m", "lnf.train", f"+experiment={scene}", "trainer=smoke", "logger=csv", "scene.mesh=[6,3]",
          "integrator.max_substeps=4",  # a 1-epoch model is stiff: no rollout crawls at 64 substeps
          "data.n_train=2", "data.n_val=1", "data.n_test=2", "data.n_times=12", "data.train_times=6",
          "data.fine_resolution=8", "data.coarse_resolution=8", "model.width=16", "model.hyper_width=8",
          "quadrature.order=[4,3]", "evaluation.long_steps=4", "evaluation.long_trajectories=1",
          "model.closure_degree=0",  # the closure's fit has tests of its own (tests/test_closure.py)
          "evaluation.figures=0",  # the script's figures are checked, not the run's
          # the cantilever's 1-epoch POD-subspace model leaves its table's box in the long speed-up rollout and
          # pays exact jets there (6 min under load): the script is what is tested, on the plain embedding
          *(["model.pod_subspace=false"] if scene == "elastic" else []),
          f"paths.data_dir={tmp_path / 'data'}", f"hydra.run.dir={run}"], png_only=True)
    out = tmp_path / "out"
    measure = ["speedup", "damped"] if scene == "elastic" else ["loads", "decay"]  # the black box and POD modes: the test above
    _run(["-m", "experiments.scenes", "--scene", scene, "--ckpt", str(run / "checkpoints" / "last.ckpt"),
          "--out", str(out), "--threads", "1", "--measure", *measure], png_only=True)
    result = json.loads((out / "results.json").read_text())
    assert result["measurements"] == measure
    assert result["integrator"]["order"] == 4  # conf/experiment/<scene>.yaml's, as lnf.train rolls out
    if scene == "elastic":
        assert result["speedup"] > 0 and len(result["rom"]) == 3 and (out / "tip.png").is_file()
        assert len(result["fom"]) == 5 and result["fom"][0]["step_factor"] == 1.0  # the FEM's own step, then larger
        assert result["damped"]["damping_per_second"] == 0.5 and (out / "damped.png").is_file()
        assert "dissipated_ratio_ours_over_reference_median" in result["damped"]
    else:
        # a 1-epoch model may diverge (nan); the decay itself is tested in tests/test_elastic.py (damping tests)
        assert "largest_energy_rise_per_sample_over_scale" in result["free_decay"] and (out / "decay.png").is_file()
        assert "field_rel_l2/in_horizon/median" in result["unseen_load"] and (out / "tip_unseen_load.png").is_file()


def test_elastic_diagnostics_smoke(tmp_path):
    """Content of both releases on a tiny mesh, and the energy, gradient, equation-residual, curve and tangent
    diagnostics of a tiny checkpoint (trained with the gradient and dynamics-residual losses), in one call."""
    reports = tmp_path / "reports"
    run = tmp_path / "run"
    _run(["-m", "lnf.train", "+experiment=elastic", "trainer=smoke", "logger=csv", "scene.mesh=[6,3]",
          "integrator.max_substeps=4",  # a 1-epoch model is stiff: no rollout crawls at 64 substeps
          "data.n_train=2", "data.n_val=1", "data.n_test=1", "data.n_times=8", "data.train_times=6",
          "data.fine_resolution=8", "data.coarse_resolution=8", "model.width=16", "model.hyper_width=8",
          "quadrature.order=[4,3]", "evaluation.long_steps=4", "evaluation.long_trajectories=1",
          "model.gradient_weight=1.0", "model.dynamics_weight=1.0", "optimizer.energy_warmup_epochs=0",
          "evaluation.figures=0",  # the diagnostics read the checkpoint, not the run's figures
          f"paths.data_dir={tmp_path / 'data'}", f"hydra.run.dir={run}"])
    fit = json.loads((run / "metrics.json").read_text())
    assert "train/gradient" in fit and "train/dynamics" in fit  # the FEM's ∇_X u and the observed ü reached the loss
    out = _run(["-m", "experiments.elastic_diagnostics", "--content", "--oracle", "--degree", "1", "2", "--runs", "2",
                "--mesh", "6", "3", "--out", str(reports), "--ckpt", str(run / "checkpoints" / "last.ckpt")]).stdout
    assert "release = 'shape'" in out and "release = 'modal'" in out and "cubic 2-D manifold" in out
    assert "oracle d = 1 reduction" in out and "rollout error in the horizon, median" in out
    oracle = (reports / "oracle" / "summary.md").read_text()  # the tables results_tables.py shows
    assert "Command: `python -m experiments.elastic_diagnostics --content --oracle --degree 1 2" in oracle
    assert "| linear (one POD mode, POD-Galerkin) |" in oracle and "| quadratic |" in oracle
    assert set(json.loads((reports / "oracle" / "oracle.json").read_text())) == {"1", "2"}
    content = (reports / "content" / "summary.md").read_text()
    assert "| `shape` |" in content and "| `modal` (the default) |" in content
    assert "T_FEM" in out and "velocity-gradient relative error" in out and "relative residual, median" in out
    assert "FEM through φ: small-amplitude period" in out and "model: rollout error in the horizon" in out
    assert "period of the learned tangent under the FEM's K_t" in out


def test_streaming_benchmark_smoke(tmp_path):
    """experiments/streaming.py on a tiny dataset: it needs a writable memory cgroup, and says so without one."""
    out = tmp_path / "results.json"
    proc = subprocess.run([sys.executable, "-m", "experiments.streaming", "--gib", "0.02", "--limit-gib", "1.5",
                           "--steps", "2", "--warmup", "1", "--loader-batches", "3", "--runs", "lazy,in_memory",
                           "--data-dir", str(tmp_path / "data"),
                           "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    if "needs a writable memory cgroup" in proc.stderr:
        assert proc.returncode != 0 and not out.exists()
        return
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    runs = {(r["mode"], r["workers"], r["limit_bytes"] is not None): r for r in result["runs"]}
    lazy, baseline = runs[("lazy", 0, True)], runs[("in_memory", 0, False)]
    assert lazy["returncode"] == 0 and lazy["train_snapshots_per_s"] > 0 and lazy["peak_rss_bytes"] > 0
    assert baseline["train_rate_vs_in_memory"] == 1.0 and lazy["limit_bytes"] == int(1.5 * 2 ** 30)
    summary = (tmp_path / "summary.md").read_text()  # the table results_tables.py shows in docs/scaling.md
    assert "Command: `python -m experiments.streaming --gib 0.02" in summary and "Machine: " in summary
    assert "| streaming, 1.5 GiB limit |" in summary and "| in memory, no limit (the baseline, same run) |" in summary
    assert summary.rstrip().endswith("| 1.00 |")


def test_baselines_drop_the_neural_settings_of_a_scene_experiment():
    """+experiment=bump sets a SIREN width: POD and the full-order model must not receive it."""
    from experiments import studylib as S

    study = S.Study(name="x", scene="bump", mode="reduced", out=ROOT / "outputs" / "unused", threads=1)
    assert {"~model.width", "~model.reduction_starts"} <= set(study.method("pod"))
    assert not any(o.startswith("~") for o in study.method("lnf"))
    pendulum = S.Study(name="x", scene="pendulum", mode="reduced", out=ROOT / "outputs" / "unused", threads=1)
    # the pendulum pins its SIREN's frequency (model.w0; the model's default is auto) and width, and its gradient
    # loss: POD drops just those
    assert [o for o in pendulum.method("pod") if o.startswith("~")] == ["~model.gradient_weight", "~model.w0",
                                                                         "~model.width"]


def test_rayleigh_ritz_of_the_exact_mode():
    """A curve whose tangent at rest is the FEM's first mode has the FEM's period and no tangent error; adding a
    stiff (axial) component to the tangent shortens the period, as Rayleigh–Ritz says it must."""
    import numpy as np
    import torch

    from experiments.elastic_diagnostics import rayleigh_ritz

    from lnf.scenes.elastic import ElasticCantilever

    scene = ElasticCantilever(mesh=(8, 4), release="modal")
    u_g, mode, _ = scene.modal_reference()
    axial = np.stack([scene.body.nodes[:, 0] ** 2, 0 * scene.body.nodes[:, 0]], -1)  # u₁ ∝ X₁²: pure stretching

    class Curve:  # u(q) = u_g + q (φ₁ + ε a), rest at q = 0
        def __init__(self, eps: float) -> None:
            self.scene, self.tangent = scene, torch.as_tensor(mode + eps * axial)
            self.field = self

        def jet(self, q, nodes, order):
            value = torch.as_tensor(u_g)[None] + q[:, :, None] * self.tangent[None]
            return type("Jet", (), {"value": value, "J": self.tangent[None, ..., None].expand(len(q), -1, -1, 1)})()

        def lagrangian_dynamics(self):
            return type("Dyn", (), {"potential_energy": staticmethod(lambda q: q[:, 0] ** 2)})()

    exact = rayleigh_ritz(Curve(0.0), -1.0, 1.0)
    first, learned = exact["period of the FEM's first mode [s]"], exact["period of the learned tangent under the FEM's K_t [s]"]
    assert learned == pytest.approx(first, rel=1e-6)
    assert exact["tangent error, share of the mass norm"] < 1e-6
    stiff = rayleigh_ritz(Curve(0.05), -1.0, 1.0)
    assert stiff["period of the learned tangent under the FEM's K_t [s]"] < 0.99 * first
    assert stiff["tangent error, share of the strain energy (eᵀK_t e / c²φ₁ᵀK_tφ₁)"] > 0.01


def test_pareto_leaves_out_quadrature_rules_too_large_for_the_body(capsys):
    """32³ Gauss–Legendre points on a 3-D body took 24 GB in one evaluation job: such rules are left out, by name."""
    from experiments import pareto

    class Study:
        name = "pareto-x"

        def __init__(self, dim):
            self.dim = dim

        def scene_object(self):
            return type("Scene", (), {"body_dim": self.dim})()

    assert pareto._within_points(Study(2), "4,8,12,16,32", "orders") == "4,8,12,16,32"
    assert pareto._within_points(Study(3), "4,8,12,16,32", "orders") == "4,8,12,16"
    assert "orders 32 left out" in capsys.readouterr().out


def test_scenes_script_never_writes_a_checkpoints_data_path_outside_the_data_folder(tmp_path, monkeypatch):
    """experiments/scenes.py regenerated (or replaced) the file a checkpoint's data.path named, as lnf.evaluate once
    did: outside the data folder it is only read, and other settings are generated into the data folder."""
    import hashlib
    import shutil

    import torch

    from experiments import scenes
    from helpers import TINY, compose_config

    import lnf
    from lnf.train import train

    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "trainer.max_epochs=1", "logger=csv",
                                   *TINY, "evaluation.figures=0", "evaluation.every_n_epochs=0"], tmp_path / "t")
    train(cfg)
    ckpt_path = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    data_file = Path(torch.load(ckpt_path, weights_only=True)["hyper_parameters"]["data"]["path"])
    shutil.copy(data_file, elsewhere / "mydata.h5")
    (elsewhere / "notes.txt").write_text("a user's notes")
    monkeypatch.setenv("LNF_DATA_DIR", str(tmp_path / "t" / "data"))
    for name, extra in [("mydata.h5", {"n_train": 4}), ("notes.txt", {})]:
        ckpt = torch.load(ckpt_path, weights_only=True)
        ckpt["hyper_parameters"]["data"].update(path=str(elsewhere / name), **extra)
        crafted = tmp_path / f"crafted-{name}.ckpt"
        torch.save(ckpt, crafted)
        before = hashlib.md5((elsewhere / name).read_bytes()).hexdigest()
        dm = scenes.snapshot_data_of(lnf.load(crafted))
        assert hashlib.md5((elsewhere / name).read_bytes()).hexdigest() == before
        assert Path(dm.path).parent == tmp_path / "t" / "data"
    assert sorted(p.name for p in elsewhere.iterdir()) == ["mydata.h5", "notes.txt"]


def test_seeds_study_smoke(studies):
    """The seed study: one training run per seed, the spread per error window, a verdict."""
    out, stdout = _study("seeds", studies, "--seeds", "2")
    rows = _csv(out / "seeds.csv")
    assert sorted(r["seed"] for r in rows) == ["0", "1"]
    summary = (out / "summary.md").read_text()
    assert "worst ÷ median" in summary and ("Robust" in stdout or "Not robust" in stdout)
    assert "Command: `python -m experiments.seeds --smoke --seeds 2`" in summary


def test_seed_spread_counts_a_diverged_seed_as_the_worst():
    from experiments.seeds import spread

    rows = [{"seed": 0, "field_rel_l2/all/median": 0.05, "diverged_count": 0},
            {"seed": 1, "field_rel_l2/all/median": 0.10, "diverged_count": 0},
            {"seed": 2, "field_rel_l2/all/median": float("inf"), "diverged_count": 3}]
    (all_,) = [r for r in spread(rows) if r["window"] == "all"]
    assert all_["median"] == 0.10 and all_["worst_seed"] == 2 and all_["worst_over_median"] == float("inf")
    assert all_["diverged_seeds"] == "seed 2"  # not a bare "2", which reads as a count
    rows[0]["diverged_count"] = 1
    assert spread(rows)[0]["diverged_seeds"] == "seeds 0, 2"
    assert spread([{**r, "diverged_count": 0} for r in rows])[0]["diverged_seeds"] == "none"


def test_a_sweep_run_again_with_another_command_keeps_the_old_results(tmp_path, monkeypatch):
    """A sweep folder whose command differs (another checkout, other settings), is unfinished, or meets --fresh is
    renamed aside, never deleted (it used to be removed: 70 minutes of runs lost to a rerun from another worktree)."""
    from experiments import studylib

    def fake_worker(entry, args, log):  # one finished job, as Hydra lays it out
        job = Path(next(a.split("=", 1)[1] for a in args if a.startswith("hydra.sweep.dir="))) / "0"
        job.mkdir(parents=True)
        (job / "metrics.json").write_text(json.dumps({"field_rel_l2/all/median": 0.5}))
        log.write_text("ok\n")
        return 0

    monkeypatch.setattr(studylib.study, "run_in_worker", fake_worker)
    monkeypatch.setattr(studylib.study, "collect", lambda folder, sweep, label=None: [])
    study = studylib.Study(name="x", scene="pendulum", mode="smoke", out=tmp_path, threads=1)
    study.multirun("sweep", ["model.width=8"])
    (tmp_path / "sweep" / "0" / "mine.txt").write_text("a user's file")
    study.multirun("sweep", ["model.width=8"])  # the same command, finished: reused, nothing moved
    assert [p.name for p in tmp_path.iterdir()] == ["sweep"]
    study.multirun("sweep", ["model.width=16"])  # another command: the old folder is kept aside
    kept = [p for p in tmp_path.iterdir() if p.name.startswith("sweep.replaced-")]
    assert len(kept) == 1 and (kept[0] / "0" / "mine.txt").read_text() == "a user's file"
    assert (tmp_path / "sweep" / "0" / "metrics.json").is_file()
    study.fresh = True
    study.multirun("sweep", ["model.width=16"])  # --fresh: kept aside too
    assert len([p for p in tmp_path.iterdir() if p.name.startswith("sweep.replaced-")]) == 2


def _process_ended(pid: int) -> bool:
    """Whether `pid` has exited (gone, or a zombie no one reaped yet)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] in ("Z", "X")
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc")
def test_a_study_killed_mid_job_takes_its_job_worker_with_it(tmp_path):
    """A study killed with SIGKILL (no atexit) while its worker runs a long job: the worker ends too, instead of
    training on as an orphan."""
    import signal
    import time

    log = tmp_path / "job.log"
    study = (
        "import json, sys, time\n"
        "from experiments import studylib\n"
        "worker = studylib.JobWorker()\n"
        "request = {'module': 'timeit', 'args': ['-n', '1', '-r', '1', 'import time; time.sleep(120)'],"
        f" 'log': {str(log)!r}}}\n"
        "worker.proc.stdin.write(json.dumps(request) + '\\n'); worker.proc.stdin.flush()\n"
        "print(worker.proc.pid, flush=True)\n"
        "time.sleep(300)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", study], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    worker = None
    try:
        worker = int(parent.stdout.readline())
        deadline = time.monotonic() + 120
        while not log.exists() and time.monotonic() < deadline:  # the worker has taken the job
            time.sleep(0.2)
        assert log.exists(), "the job worker never started its job"
        assert not _process_ended(worker)
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 30
        while not _process_ended(worker) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert _process_ended(worker), "the job worker outlived the study that started it"
    finally:
        parent.kill()
        parent.wait()
        if worker is not None and not _process_ended(worker):
            os.kill(worker, signal.SIGKILL)


def test_stiff_rollouts_names_a_setting_that_is_not_json():
    """experiments/stiff_rollouts.py refuses an integrator setting it cannot read (naming it) and a count below 1,
    before any data."""
    from experiments import stiff_rollouts

    with pytest.raises(SystemExit, match=r"--settings 'rk4' is not JSON"):
        stiff_rollouts.main(["--settings", "rk4"])
    with pytest.raises(SystemExit):
        stiff_rollouts.main(["--modes", "0"])
