"""`python -m lnf.evaluate` refuses what it would not use or cannot do, says where rollouts diverge, and keeps its
results when a figure fails: unknown keys (lnf.config_keys), bad values, divergence metrics and warnings."""
from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

import lnf
from helpers import CONF, ROOT, TINY, DivergesAtStep, compose_config

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("evaluate_errors")]

EXPERIMENTS = sorted(p.stem for p in (Path(CONF) / "experiment").glob("*.yaml"))


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    """One tiny pendulum checkpoint (1 epoch) shared by the tests of this file, which only read it."""
    from lnf.train import train

    tmp = tmp_path_factory.mktemp("pendulum")
    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "trainer.max_epochs=1", "logger=csv",
                                   *TINY, "evaluation.figures=0", "evaluation.every_n_epochs=0"], tmp)
    train(cfg)
    path = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    assert path.is_file()
    return path


def eval_cfg(ckpt: Path, overrides: list[str], tmp_path: Path):
    return compose_config("evaluate", [f"ckpt_path={ckpt}", "figures=0", *overrides], tmp_path)


# -- 1. unknown keys ------------------------------------------------------------------------------------------
def test_cli_refuses_a_config_group_and_a_key_it_does_not_use(ckpt, tmp_path):
    """`+scene=pendulum` used to evaluate the checkpoint's scene while run.json recorded the bogus one."""
    run_dir = tmp_path / "run"
    env = {**os.environ, "LNF_ROOT": str(tmp_path), "WANDB_MODE": "offline"}
    proc = subprocess.run([sys.executable, "-m", "lnf.evaluate", f"ckpt_path={ckpt}", "+scene=pendulum", "+foo=1",
                           "figures=0", f"hydra.run.dir={run_dir}"], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode != 0, proc.stdout[-2000:]
    assert "lnf.evaluate does not use the key(s) foo, scene" in proc.stderr, proc.stderr[-3000:]
    assert "it takes task_name, ckpt_path, split" in proc.stderr
    assert not (run_dir / "metrics.json").exists() and not (run_dir / "run.json").exists()


@pytest.mark.parametrize("override,key", [("+scene=pendulum", "scene"), ("+foo=1", "foo"),
                                          ("+grid.bar=2", "grid.bar"), ("+model=pod", "model"),
                                          ("+evaluation.long_steps=3", "evaluation")])
def test_evaluate_refuses_unknown_keys(ckpt, tmp_path, override, key):
    cfg = eval_cfg(ckpt, [override], tmp_path)
    with pytest.raises(ValueError, match=rf"lnf.evaluate does not use the key\(s\) {key}\b.*it takes task_name, ckpt_path, split, "
                                             r".*and the config groups integrator, quadrature, dynamics, paths"):
        lnf_evaluate(cfg)
    assert not (tmp_path / "out" / "metrics.json").exists()


def test_unknown_nested_key_lists_what_its_node_takes(ckpt, tmp_path):
    with pytest.raises(ValueError, match=r"grid\.kindd.*grid takes kind, resolution, n_points, seed.*did you mean "
                                         r"grid\.kind"):
        lnf_evaluate(eval_cfg(ckpt, ["+grid.kindd=uniform"], tmp_path))


def test_documented_evaluate_overrides_are_accepted(tmp_path):
    from lnf.config_keys import check_known_keys

    for overrides in (["integrator=rk4", "dt=0.01", "horizon=20", "grid.kind=uniform", "grid.resolution=128"],
                      ["quadrature=uniform", "quadrature.resolution=32", "dynamics=tabulated", "long_steps=10"],
                      ["dynamics=lagrangian", "initial_states=[[2.8,0.0]]", "threads=1", "integrator.substeps=2"]):
        check_known_keys(compose_config("evaluate", ["ckpt_path=x.ckpt", *overrides], tmp_path), "evaluate",
                         "lnf.evaluate")


@pytest.mark.parametrize("overrides", [[f"+experiment={e}"] for e in EXPERIMENTS] + [
    ["+experiment=pendulum", "hparams_search=pendulum_optuna"], ["+experiment=pendulum", "dynamics=latent_mlp"],
    ["+experiment=elastic", "model=pod", "logger=none"], ["dynamics=tabulated", "trainer=smoke", "model=full_order"],
    ["+experiment=pendulum", "evaluation.long_steps=5", "data.n_train=3"]], ids=lambda o: " ".join(o))
def test_train_config_passes_with_every_experiment_and_search(tmp_path, overrides):
    """lnf.train can call the same check: `# @package _global_` experiments may add top-level keys (tags)."""
    from lnf.config_keys import check_known_keys

    cfg = compose_config("train", overrides, tmp_path)
    check_known_keys(cfg, "train", "lnf.train", allowed_extra=("experiment",))
    check_known_keys(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]), Path(CONF) / "train.yaml",
                     "lnf.train", allowed_extra=("experiment",))


@pytest.mark.parametrize("override,key", [("+foo=1", "foo"), ("+evaluation.foo=1", "evaluation.foo"),
                                          ("+ckpt=last", "ckpt")])
def test_train_config_refuses_unknown_keys(tmp_path, override, key):
    from lnf.config_keys import check_known_keys

    cfg = compose_config("train", ["+experiment=pendulum", override], tmp_path)
    with pytest.raises(ValueError, match=rf"lnf.train does not use the key\(s\) {key}\b.*it takes task_name, seed, .*tags"
                                             r".*and the config groups scene, model, .*experiment"):
        check_known_keys(cfg, "train", "lnf.train", allowed_extra=("experiment",))


def test_check_known_keys_derives_the_keys_from_any_primary_file(tmp_path):
    """Keys of the file, its defaults' groups, `_global_` group options' keys and sub-keys of its plain nodes."""
    from lnf.config_keys import allowed_keys, check_known_keys

    (tmp_path / "opt").mkdir()
    (tmp_path / "opt" / "a.yaml").write_text("# a comment\n# @package _global_\nextra: 1\nnode:\n  y: 2\n")
    (tmp_path / "opt" / "b.yaml").write_text("z: 3\n")
    primary = tmp_path / "main.yaml"
    primary.write_text("defaults:\n  - opt: b\n  - _self_\nalpha: 1\nnode:\n  x: 1\n  deep:\n    k: 0\n")
    allowed = allowed_keys(primary)
    assert allowed["opt"] is None and allowed["alpha"] is None and allowed["extra"] is None
    assert allowed["node"] == {"x": None, "deep": {"k": None}, "y": None} and "hydra" in allowed
    good = OmegaConf.create({"alpha": 2, "opt": {"anything": 1}, "node": {"x": 1, "deep": {"k": 1}}, "hydra": {}})
    check_known_keys(good, primary, "tool")
    bad = OmegaConf.create({"alpha": 2, "beta": 1, "node": {"x": 1, "deep": {"k": 1, "q": 2}}})
    with pytest.raises(ValueError, match=r"tool does not use the key\(s\) beta, node\.deep\.q.*node\.deep takes k"):
        check_known_keys(bad, primary, "tool")
    check_known_keys(bad, primary, "tool", allowed_extra=("beta", "node.deep.q"))
    with pytest.raises(FileNotFoundError, match="missing.yaml"):
        check_known_keys(good, tmp_path / "missing.yaml", "tool")


# -- 2. bad values --------------------------------------------------------------------------------------------
BAD_VALUES = [
    ("dt=nan", r"dt must be a finite number > 0 \[s\].*got nan"),
    ("dt=inf", r"dt must be a finite number > 0 \[s\].*got inf"),
    ("dt=0", r"dt must be a finite number > 0 \[s\].*got 0"),
    ("dt=-0.05", r"dt must be a finite number > 0 \[s\].*got -0.05"),
    ("dt=abc", r"dt must be a finite number > 0 \[s\].*got 'abc'"),
    ("dt=true", r"dt must be a finite number > 0 \[s\].*got True"),
    ("horizon=inf", r"horizon must be a finite number > 0 \[s\].*got inf"),
    ("horizon=nan", r"horizon must be a finite number > 0 \[s\].*got nan"),
    ("horizon=-1", r"horizon must be a finite number > 0 \[s\].*got -1"),
    ("horizon=abc", r"horizon must be a finite number > 0 \[s\].*got 'abc'"),
    ("train_horizon=nan", r"train_horizon must be a finite number > 0 \[s\].*got nan"),
    # extrapolation from t = 0 (nothing before it) or from before it: used to pass silently
    ("train_horizon=0", r"train_horizon must be a finite number > 0 \[s\] \(where extrapolation starts; 0 leaves "
                        r"no time before it\).*got 0"),
    ("train_horizon=-1", r"train_horizon must be a finite number > 0 \[s\].*got -1"),
    # a horizon that is not a whole number of dt used to be rounded (1.0 at 0.3 covered 0.9 s); one frame crashed
    ("dt=0.3 horizon=1.0", r"horizon=1 \[s\] at dt=0.3 \[s\] is 3.33333 steps of dt, not a whole number: .*would "
                           r"cover 0.9 s instead of 1 s; set horizon=0.9 or horizon=1.2 \(a whole number of dt\)"),
    ("dt=0.05 horizon=0.06", r"horizon=0.06 \[s\] at dt=0.05 \[s\] is 1.2 steps of dt.*; set horizon=0.1 \("),
    ("dt=0.05 horizon=0.05", r"horizon=0.05 \[s\] at dt=0.05 \[s\] is 1 frame: a rollout needs at least 2 frames"),
    ("dt=0.05 horizon=1 train_horizon=100", r"train_horizon=100 \[s\] \(where extrapolation starts\) is beyond "
                                            r"the evaluated horizon=1 \[s\] at dt=0.05 \[s\]: no frame would come "
                                            r"after it; set train_horizon ≤ 1"),
    ("max_trajectories=0", r"max_trajectories must be an integer ≥ 1.*got 0"),
    ("max_trajectories=-3", r"max_trajectories must be an integer ≥ 1.*got -3"),
    ("max_trajectories=1.5", r"max_trajectories must be an integer ≥ 1.*got 1.5"),
    ("max_trajectories=abc", r"max_trajectories must be an integer ≥ 1.*got 'abc'"),
    ("max_trajectories=inf", r"max_trajectories must be an integer ≥ 1.*got inf"),
    ("long_steps=-1", r"long_steps must be an integer ≥ 0.*got -1"),
    ("long_steps=abc", r"long_steps must be an integer ≥ 0.*got 'abc'"),
    ("long_trajectories=0", r"long_trajectories must be an integer ≥ 1.*got 0"),
    ("figures=-1", r"figures must be an integer ≥ 0.*got -1"),
    ("figures=nan", r"figures must be an integer ≥ 0.*got nan"),
    ("max_reduction_points=0", r"max_reduction_points must be an integer ≥ 1.*got 0"),
    ("threads=-1", r"threads must be an integer ≥ 1.*got -1"),
    ("split=foo", r"split must be one of train, val, test, got 'foo'"),
    ("grid.kind=hex", r"grid.kind must be 'stored', 'uniform' or 'random', got 'hex'"),
    ("grid.resolution=abc", r"grid.resolution must be an integer ≥ 1.*got 'abc'"),
    ("grid.n_points=0", r"grid.n_points must be an integer ≥ 1.*got 0"),
    ("max_steps=0", r"max_steps must be an integer ≥ 1 \(the most integration steps.*or null \(no limit\), got 0"),
    ("max_memory_gb=nan", r"max_memory_gb must be a finite number > 0 \[GB\].*got nan"),
    ("max_memory_gb=-1", r"max_memory_gb must be a finite number > 0 \[GB\].*got -1"),
    # every number the validators know, in the integrator, quadrature and dynamics groups too
    ("integrator.tol=nan", r"integrator\.tol must be a finite number > 0 \(the tolerance of the implicit solve\), got nan"),
    ("integrator.substeps=nan", r"integrator\.substeps must be an integer ≥ 1.*got nan"),
    ("integrator.max_iter=0", r"integrator\.max_iter must be an integer ≥ 1.*got 0"),
    ("quadrature=uniform quadrature.resolution=inf", r"quadrature\.resolution must be a finite number, got inf"),
    ("dynamics=tabulated dynamics.tol=nan", r"dynamics\.tol must be a finite number > 0.*got nan"),
    ("initial_states=[[0.5,nan]]", r"initial_states\[0\]\[1\] must be a finite number, got nan"),
]


@pytest.mark.parametrize("override,match", BAD_VALUES, ids=[o for o, _ in BAD_VALUES])
def test_bad_values_are_refused_before_anything_is_loaded(ckpt, tmp_path, monkeypatch, override, match):
    import lnf.evaluate

    def no_load(*args, **kwargs):
        raise AssertionError("the checkpoint was loaded before the settings were checked")

    monkeypatch.setattr(lnf.evaluate, "load", no_load)
    with pytest.raises(ValueError, match=match):
        lnf.evaluate.evaluate(eval_cfg(ckpt, override.split(), tmp_path))


# Work that cannot finish is refused before any data are loaded or simulated: the time budget (max_steps
# integration steps, integrator.substeps counted) and the memory (max_memory_gb, $LNF_MAX_MEMORY_GB, else what is
# available). Each used to end in a numpy allocation error after a while, or to run with memory rising.
OVER_BUDGET = [
    (["horizon=1e9"], r"horizon=1e\+09 \[s\] at dt=null \(the data’s: 0.05 s\) is 20000000000 frames: with "
                      r"integrator.substeps=1 the rollout takes 2e\+10 integration steps per trajectory, over "
                      r"max_steps=1000000 \(the time budget of lnf.evaluate\): lower horizon, raise dt"),
    (["horizon=1e5"], r"horizon=100000 .* 2e\+06 integration steps per trajectory, over max_steps=1000000"),
    (["horizon=2e4", "integrator.substeps=100"], r"horizon=20000 .*is 400000 frames: with integrator.substeps=100 "
                                                 r"the rollout takes 4e\+07 integration steps"),
    (["long_steps=1e9"], r"long_steps=1e\+09 with integrator.substeps=1 is 1e\+09 integration steps, over "
                         r"max_steps=1000000.*lower long_steps"),
    (["long_steps=20000", "integrator=rk4", "integrator.substeps=100"],
     r"long_steps=20000 with integrator.substeps=100 is 2e\+06 integration steps, over max_steps=1000000"),
    (["grid.kind=uniform", "grid.resolution=100000", "max_memory_gb=64"],
     r"the evaluation would hold about 6\d\d\.\d GB \(2 trajectories × 20 frames × 10000000000 points: .*"
     r"grid.kind=uniform, grid.resolution=100000.*\), over the limit of 64.0 GB \(max_memory_gb=64\): .*fewer points"),
    (["grid.kind=random", "grid.n_points=1e12", "max_memory_gb=64"],
     r"the evaluation would hold about \d+\.\d GB .*grid.n_points=1e\+12.*over the limit of 64.0 GB"),
    (["horizon=1e4", "max_steps=null", "max_memory_gb=0.01"],
     r"the evaluation would hold about .* MB \(2 trajectories × 200000 frames .*horizon=10000 \[s\].*over the "
     r"limit of 10.2 MB \(max_memory_gb=0.01\): lower horizon"),
    (["long_steps=1e8", "max_steps=null", "max_memory_gb=0.1"],
     r"long_steps=1e\+08 × long_trajectories=2 would hold about 1.5 GB .*over the limit of 102.4 MB"),
]


@pytest.mark.parametrize("overrides,match", OVER_BUDGET, ids=[" ".join(o) for o, _ in OVER_BUDGET])
def test_work_that_cannot_finish_is_refused_before_any_data_is_loaded(ckpt, tmp_path, monkeypatch, overrides, match):
    import lnf.evaluate

    def no_data(*args, **kwargs):
        raise AssertionError("data were loaded or simulated before the budget was checked")

    for name in ("lnf.dataset.reuse.ensure_dataset", "lnf.evaluation_pipeline.verify_dataset", "lnf.evaluate.load_split",
                 "lnf.evaluation_settings.simulated_ground_truth", "lnf.evaluation_pipeline.evaluate_rollouts"):
        monkeypatch.setattr(name, no_data)
    with pytest.raises(ValueError, match=match):
        lnf.evaluate.evaluate(eval_cfg(ckpt, overrides, tmp_path))


# Times checked against the data's own dt and horizon (20 samples at 0.05 s), still before any data are loaded
DATA_TIMES = [
    (["horizon=0.06"], r"horizon=0.06 \[s\] at dt=null \(the data’s: 0.05 s\) is 1.2 steps of dt, not a whole "
                       r"number.*set horizon=0.1 \(a whole number of dt\)"),
    (["dt=0.03"], r"horizon=null \(the data’s: 1 s\) at dt=0.03 \[s\] is 33.3333 steps of dt.*set "
                  r"horizon=0.99 or horizon=1.02"),
    (["train_horizon=100"], r"train_horizon=100 \[s\] \(where extrapolation starts\) is beyond the evaluated "
                            r"horizon=null \(the data’s: 1 s\)"),
]


@pytest.mark.parametrize("overrides,match", DATA_TIMES, ids=[" ".join(o) for o, _ in DATA_TIMES])
def test_times_that_do_not_fit_the_data_are_refused_before_any_data_is_loaded(ckpt, tmp_path, monkeypatch,
                                                                               overrides, match):
    import lnf.evaluate

    def no_data(*args, **kwargs):
        raise AssertionError("data were loaded or simulated before the times were checked")

    for name in ("lnf.dataset.reuse.ensure_dataset", "lnf.evaluation_pipeline.verify_dataset", "lnf.evaluate.load_split",
                 "lnf.evaluation_settings.simulated_ground_truth", "lnf.evaluation_pipeline.evaluate_rollouts"):
        monkeypatch.setattr(name, no_data)
    with pytest.raises(ValueError, match=match):
        lnf.evaluate.evaluate(eval_cfg(ckpt, overrides, tmp_path))


def test_rollout_frames_are_a_whole_number_of_dt_to_rounding():
    from lnf.evaluation_settings import rollout_frames

    cfg = OmegaConf.create({"dt": None, "horizon": None, "train_horizon": None})
    assert rollout_frames(cfg, 0.1, 1.0) == 10 and rollout_frames(cfg, 0.05, 0.1) == 2  # 1.0/0.1 = 10.000000000000002
    assert rollout_frames(cfg, 0.01, 0.3) == 30 and rollout_frames(cfg, 0.05, 1e9) == 20_000_000_000
    with pytest.raises(ValueError, match=r"horizon=null \(the data’s: 1 s\) at dt=null \(the data’s: 0.3 s\) is "
                                         r"3.33333 steps"):
        rollout_frames(cfg, 0.3, 1.0)
    # train_horizon at the horizon passes here (nothing after it: a warning when the rollout runs), beyond it not
    assert rollout_frames(OmegaConf.create({"train_horizon": 1.0}), 0.1, 1.0) == 10
    with pytest.raises(ValueError, match=r"train_horizon=1.5 \[s\]"):
        rollout_frames(OmegaConf.create({"train_horizon": 1.5}), 0.1, 1.0)


def test_memory_limit_from_the_environment_and_the_machine(ckpt, tmp_path, monkeypatch):
    import lnf.evaluate
    import lnf.evaluation_cost

    found, where = lnf.evaluation_cost.available_memory()  # read portably: /proc/meminfo, a cgroup limit, os.sysconf
    assert found is None or found > 0, where
    monkeypatch.setenv("LNF_MAX_MEMORY_GB", "0.001")
    with pytest.raises(ValueError, match=r"over the limit of 1.0 MB \(\$LNF_MAX_MEMORY_GB=0.001\)"):
        lnf.evaluate.evaluate(eval_cfg(ckpt, ["grid.kind=uniform", "grid.resolution=200"], tmp_path))
    monkeypatch.setenv("LNF_MAX_MEMORY_GB", "lots")
    with pytest.raises(ValueError, match=r"\$LNF_MAX_MEMORY_GB='lots' must be a finite number > 0 \[GB\]"):
        lnf.evaluate.evaluate(eval_cfg(ckpt, [], tmp_path))
    # max_memory_gb wins over the environment; the substeps are in the cost line
    with caplog_at(logging.INFO, "lnf.evaluate") as records:
        lnf.evaluate.evaluate(eval_cfg(ckpt, ["max_memory_gb=8", "max_trajectories=1", "integrator=rk4",
                                              "integrator.substeps=3", "long_steps=5", "long_trajectories=1"],
                                       tmp_path))
    said = " ".join(r.getMessage() for r in records)
    assert "the rollout takes 57 integration steps per trajectory (19 sample intervals × integrator.substeps=3)" \
        in said, said
    assert "1 trajectories × 5 steps (15 integration steps with integrator.substeps=3)" in said, said


@contextlib.contextmanager
def caplog_at(level, name):
    """The records of logger `name` at `level` and above (a caplog that does not need the fixture)."""
    records = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record)

    logger, handler = logging.getLogger(name), Keep(level)
    old = logger.level
    logger.addHandler(handler)
    logger.setLevel(level)
    try:
        yield records
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old)


def test_missing_checkpoint_path_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match=r"ckpt_path is required"):
        lnf_evaluate(compose_config("evaluate", [], tmp_path))


# -- 3. divergence with a place -------------------------------------------------------------------------------
def _setup(ckpt):
    model = lnf.load(ckpt)
    scene = model.scene
    times = 0.05 * np.arange(12)
    states = scene.simulate(np.array([[0.5, 0.0], [1.0, 0.2]]), times)
    from lnf.quadrature import midpoint_grid

    return model, states, times, midpoint_grid(8, scene.bounds).numpy()


def test_rollout_divergence_metrics_and_warning(ckpt, caplog):
    from lnf.evaluation import evaluate_rollouts

    model, states, times, points = _setup(ckpt)
    with caplog.at_level(logging.WARNING, logger="lnf.evaluation"):
        res = evaluate_rollouts(model, states, times, points, 0.3, integrator=DivergesAtStep(3),
                                label="test rollout")
    m = res.metrics
    assert m["diverged_count"] == 1.0 and m["diverged_fraction"] == 0.5
    assert m["first_divergence_step"] == 3.0 and m["first_divergence_time"] == pytest.approx(0.15)
    assert np.isnan(res.q_pred[1, 3:]).all() and np.isfinite(res.q_pred[0]).all()
    warned = [r.getMessage() for r in caplog.records if r.name == "lnf.evaluation" and r.levelno == logging.WARNING]
    assert any("test rollout" in w and "1 of 2 trajectories diverged" in w and "step 3" in w and "t = 0.15 s" in w
               for w in warned), warned

    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="lnf.evaluation"):
        fine = evaluate_rollouts(model, states, times, points, 0.3, integrator="rk4").metrics
    assert fine["diverged_count"] == 0.0 and fine["diverged_fraction"] == 0.0
    assert fine["first_divergence_step"] == -1.0 and fine["first_divergence_time"] == -1.0
    assert not [r for r in caplog.records if r.name == "lnf.evaluation" and r.levelno >= logging.WARNING]


class NaNPotential:
    """A scene's discrete potential that is NaN everywhere (a user's potential() with a bug)."""

    def __init__(self, inner):
        self.inner, self.needs_gradient = inner, inner.needs_gradient

    def __call__(self, q, G=None):
        return self.inner(q, G) * float("nan")

    def gradient(self, q, G=None):
        dq, dG = self.inner.gradient(q, G)
        return dq * float("nan"), dG


def test_divergence_at_a_non_finite_initial_state_names_the_cause_not_the_step(ckpt, caplog, monkeypatch):
    """A scene whose potential is NaN at the initial state used to read "diverged at step 0 … try a smaller dt"."""
    import torch

    from lnf.evaluation import evaluate_rollouts, long_horizon_energy
    from lnf.integrators import RolloutDivergedError

    model, states, times, points = _setup(ckpt)
    potential = model.scene.potential
    monkeypatch.setattr(model.scene, "potential", lambda quadrature: NaNPotential(potential(quadrature)))
    for integrator in ("rk4", "implicit_midpoint"):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="lnf.evaluation"):
            m = evaluate_rollouts(model, states, times, points, 0.3, integrator=integrator, label="test rollout").metrics
        assert m["diverged_count"] == 2.0 and m["first_divergence_step"] == 0.0
        warned = " ".join(r.getMessage() for r in caplog.records if r.name == "lnf.evaluation")
        assert "the potential energy Ṽ(q̃0) is nan at its initial state: the scene's potential is non-finite" in warned
        assert "This is not a step-size problem" in warned and "smaller dt," not in warned, warned
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="lnf.evaluation"):
        long_horizon_energy(model, states[:, 0], points, 0.05, 20, integrator="rk4")
    warned = " ".join(r.getMessage() for r in caplog.records if r.name == "lnf.evaluation")
    assert "long-horizon energy check" in warned and "the potential energy Ṽ(q̃0) is nan" in warned, warned
    for integrator in ("rk4", "implicit_midpoint", "dopri5"):  # the Python API's rollout raises, naming the cause
        with pytest.raises(RolloutDivergedError, match=r"the acceleration is already non-finite at the initial state"
                                                       r".*This is not a step-size problem"):
            model.rollout(torch.zeros(2, 1), torch.zeros(2, 1), dt=0.05, steps=3, integrator=integrator)


def test_divergence_on_the_way_is_read_against_the_fastest_reduced_frequency(ckpt, caplog):
    """A rollout that starts finite and diverges on the way: the warning reads the step against the fastest reduced
    frequency at the last finite state (here the step resolves it: a smaller step is not the cure), not an
    initial-state cause. (It used to suggest a smaller dt whatever the cause.)"""
    from lnf.evaluation import evaluate_rollouts

    model, states, times, points = _setup(ckpt)
    with caplog.at_level(logging.WARNING, logger="lnf.evaluation"):
        evaluate_rollouts(model, states, times, points, 0.3, integrator=DivergesAtStep(3), label="test rollout")
    warned = " ".join(r.getMessage() for r in caplog.records if r.name == "lnf.evaluation")
    assert "Trajectories [1]: at the last finite state the fastest reduced frequency is ω_max = " in warned, warned
    assert "the step resolves it, so the step size is not the cause" in warned and "step-size" not in warned


def test_automatic_substeps_are_reported_where_they_rose(ckpt, caplog):
    """A step the integrator finds stiff (here an RK4 that asks for 3 substeps wherever it looks; reading ω_max is
    tested in tests/test_integrators.py) is taken in more substeps; the evaluation reports how many (`substeps`,
    `substeps_long`) and logs it. A rollout that is not stiff reports nothing."""
    from lnf.evaluation import evaluate_rollouts, long_horizon_energy
    from lnf.integrators import RK4

    class TightRK4(RK4):
        def substeps_for(self, dynamics, q, v, dt, t, at_least, rows=None):
            return max(at_least, 3)

    model, states, times, points = _setup(ckpt)
    with caplog.at_level(logging.INFO, logger="lnf.evaluation"):
        m = evaluate_rollouts(model, states, times, points, 0.3, integrator=TightRK4(), label="test rollout").metrics
        long = long_horizon_energy(model, states[:, 0], points, 0.05, 20, integrator=TightRK4())
    assert m["substeps"] == 3 and long["substeps_long"] == 3 and m["diverged_count"] == 0.0
    logged = " ".join(r.getMessage() for r in caplog.records if r.name == "lnf.evaluation")
    assert f"test rollout: the step dt = 0.05 s was stiff against the fastest reduced frequency: {int(m['substeps'])} " \
           "substeps from the start" in logged, logged
    plain = evaluate_rollouts(model, states, times, points, 0.3, integrator="rk4").metrics
    assert "substeps" not in plain


def test_long_horizon_divergence_metrics_and_warning(ckpt, caplog):
    from lnf.evaluation import long_horizon_energy

    model, states, times, points = _setup(ckpt)
    with caplog.at_level(logging.WARNING, logger="lnf.evaluation"):
        out = long_horizon_energy(model, states[:, 0], points, 0.05, 40, integrator=DivergesAtStep(7, which=0))
    assert out["diverged_count_long"] == 1.0 and out["diverged_fraction_long"] == 0.5
    assert out["first_divergence_step_long"] == 7.0 and out["first_divergence_time_long"] == pytest.approx(0.35)
    assert np.isinf(out["energy_drift_long/max"]) and "energy_drift_long/median" in out  # existing keys stay
    warned = [r.getMessage() for r in caplog.records if r.name == "lnf.evaluation" and r.levelno == logging.WARNING]
    assert any("long-horizon energy check" in w and "1 of 2 trajectories diverged" in w and "step 7" in w
               for w in warned), warned

    fine = long_horizon_energy(model, states[:, 0], points, 0.05, 40, integrator="rk4")
    assert fine["diverged_count_long"] == 0.0 and fine["diverged_fraction_long"] == 0.0
    assert fine["first_divergence_step_long"] == -1.0 and fine["first_divergence_time_long"] == -1.0


def test_long_horizon_non_finite_energy_counts_as_divergence(ckpt, monkeypatch):
    """A rollout whose states stay finite but whose energy does not (diverged_step −1) is reported too."""
    from lnf.evaluation import long_horizon_energy

    model, states, times, points = _setup(ckpt)
    energy = model.energy

    def nan_energy(q, v, quadrature=None):
        kin, pot = energy(q, v, quadrature)
        kin = kin.clone().reshape(len(states), -1)  # the check's states in one batch: (trajectories, recorded samples)
        kin[1, 2:] = float("inf")  # recorded sample 2 = step 20 (record_every = 10)
        return kin.reshape(-1), pot

    monkeypatch.setattr(model, "energy", nan_energy)
    out = long_horizon_energy(model, states[:, 0], points, 0.05, 40, integrator="rk4")
    assert out["diverged_count_long"] == 1.0 and out["first_divergence_step_long"] == 20.0
    assert out["first_divergence_time_long"] == pytest.approx(1.0) and np.isinf(out["energy_drift_long/max"])


def test_evaluate_writes_divergence_metrics(ckpt, tmp_path):
    metrics = lnf_evaluate(eval_cfg(ckpt, ["integrator=rk4", "long_steps=10", "long_trajectories=1",
                                           "max_trajectories=1"], tmp_path))
    saved = json.loads((tmp_path / "out" / "metrics.json").read_text())
    for key in ("diverged_count", "diverged_fraction", "first_divergence_step", "first_divergence_time",
                "diverged_count_long", "diverged_fraction_long", "first_divergence_step_long",
                "first_divergence_time_long"):
        assert key in saved and saved[key] == metrics[key], key
    if metrics["diverged_count"] == 0:
        assert metrics["first_divergence_step"] == -1.0 and metrics["first_divergence_time"] == -1.0


# -- 4. a figure cannot cost the results ----------------------------------------------------------------------
def test_failing_figure_keeps_metrics_and_run_record(ckpt, tmp_path, monkeypatch, caplog):
    import lnf.evaluate

    def broken(*args, **kwargs):
        raise RuntimeError("no display for matplotlib")

    monkeypatch.setattr("lnf.evaluation_pipeline.save_evaluation_figures", broken)
    cfg = compose_config("evaluate", [f"ckpt_path={ckpt}", "figures=1", "max_trajectories=1"], tmp_path)
    with caplog.at_level(logging.WARNING, logger="lnf.evaluate"):
        metrics = lnf.evaluate.evaluate(cfg)
    out = tmp_path / "out"
    assert json.loads((out / "metrics.json").read_text()) == pytest.approx(metrics)
    assert json.loads((out / "run.json").read_text())["config"]["ckpt_path"] == str(ckpt)
    assert any("could not draw Figure 3" in r.getMessage() and "no display for matplotlib" in r.getMessage()
               for r in caplog.records if r.name == "lnf.evaluate" and r.levelno == logging.WARNING)


def lnf_evaluate(cfg):
    from lnf.evaluate import evaluate

    return evaluate(cfg)
