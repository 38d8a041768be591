"""End to end: `+experiment=pendulum` for 2 epochs on tiny data, checkpoint reload, re-evaluation, CLI."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

import lnf
from helpers import METRICS_ONLY, TINY, compose_config
from lnf.evaluate import evaluate
from lnf.integrators import RK4, get_integrator
from lnf.tabulated import TABLE_OFF_BOX_WARN
from lnf.train import train

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("run")
    # the tests of this run check its test metrics, figures, long-horizon check and checkpoint, never a validation
    # rollout: none at validation time
    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", *TINY, "evaluation.every_n_epochs=0"], tmp)
    metrics = train(cfg)
    return tmp, cfg, metrics


def test_run_writes_metrics_checkpoint_figures_and_wandb(trained):
    tmp, cfg, metrics = trained
    out = Path(cfg.paths.output_dir)
    saved = json.loads((out / "metrics.json").read_text())
    for key in ["field_rel_l2/all/median", "field_rel_l2/in_horizon/median", "field_rel_l2/extrapolation/median",
                "field_rel_l2/all/max", "projection_rel_l2/all/median", "latent_rmse/median", "energy_rel_err/max",
                "energy_drift/max", "energy_drift_long/max", "vpt/median", "rollout_seconds_per_trajectory"]:
        assert key in saved and np.isfinite(saved[key]), key
    assert saved == pytest.approx(metrics)
    assert (out / "checkpoints" / "last.ckpt").is_file()
    assert len(list((out / "figures").glob("*.png"))) >= 1
    assert list((out / "wandb").glob("offline-run-*")), "no offline wandb run"
    run = json.loads((out / "run.json").read_text())
    assert run["versions"]["torch"] and run["config"]["model"]["latent_dim"] == 1
    assert not list(out.rglob("*.tmp-*"))


def test_checkpoint_loads_without_hydra_and_gives_same_rollout(trained):
    tmp, cfg, _ = trained
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    code = f"""
import torch, lnf, sys
m = lnf.load({str(ckpt)!r})
assert 'hydra' not in sys.modules, 'lnf.load imported hydra'
q0 = torch.tensor([[0.3], [-0.2]]); v0 = torch.tensor([[0.1], [0.4]])
t = m.rollout(q0, v0, dt=0.05, steps=20, integrator='rk4')
torch.save(t.q, {str(tmp / 'q.pt')!r})
"""
    subprocess.run([sys.executable, "-c", code], check=True, cwd=tmp)
    model = lnf.load(ckpt)
    q0 = torch.tensor([[0.3], [-0.2]]); v0 = torch.tensor([[0.1], [0.4]])
    ref = model.rollout(q0, v0, dt=0.05, steps=20, integrator="rk4").q
    torch.testing.assert_close(torch.load(tmp / "q.pt"), ref)
    # the full Python API on arbitrary points
    pts = torch.rand(37, 2) * 2 - 1
    fields = model.decode(ref[:, -1], pts)
    assert fields.shape == (2, 37, 1)
    q = model.reduce(pts, fields)
    assert q.shape == (2, 1)
    v = model.project_velocity(q, pts, fields)
    T, V = model.energy(ref, torch.zeros_like(ref))
    assert T.shape == V.shape == (2, 21) and v.shape == (2, 1)


def test_evaluate_entry_point_with_overrides(trained, tmp_path):
    _, cfg, _ = trained
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    for overrides in (["integrator=rk4", "dt=0.025", "horizon=1.5", "grid.kind=random", "grid.n_points=50"],
                      ["integrator=dopri5", "grid.kind=uniform", "grid.resolution=10", "quadrature=uniform",
                       "quadrature.resolution=8", "long_steps=10"]):
        ecfg = compose_config("evaluate", [f"ckpt_path={ckpt}", *overrides], tmp_path)
        metrics = evaluate(ecfg)
        # a 2-epoch model may have a singular M̃ somewhere: that is reported as divergence, never a crash
        assert np.isfinite(metrics["field_rel_l2/all/median"]) or metrics["diverged_fraction"] > 0
        assert (tmp_path / "out" / "metrics.json").is_file()


def test_evaluate_rejects_empty_grid(trained, tmp_path):
    _, cfg, _ = trained
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    ecfg = compose_config("evaluate", [f"ckpt_path={ckpt}", "grid.kind=uniform", "grid.resolution=0"], tmp_path)
    with pytest.raises(ValueError, match="no points"):
        evaluate(ecfg)


def test_evaluate_from_given_initial_states(trained, tmp_path):
    _, cfg, _ = trained
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    metrics = evaluate(compose_config("evaluate", [f"ckpt_path={ckpt}", "initial_states=[[2.8,0.0],[0.0,7.0]]",
                                                   "figures=0"], tmp_path))
    assert "field_rel_l2/all/median" in metrics
    with pytest.raises(ValueError, match="initial_states must be a list of finite full-order states, each of 2"):
        evaluate(compose_config("evaluate", [f"ckpt_path={ckpt}", "initial_states=[[2.8]]"], tmp_path))
    states = tmp_path / "states.npy"  # large states (the elastic mesh) come as a file
    np.save(states, np.array([[2.8, 0.0]]))
    again = evaluate(compose_config("evaluate", [f"ckpt_path={ckpt}", f"initial_states={states}", "figures=0"], tmp_path))
    assert np.isfinite(again["field_rel_l2/all/median"])
    with pytest.raises(ValueError, match="existing .npy file"):
        evaluate(compose_config("evaluate", [f"ckpt_path={ckpt}", f"initial_states={tmp_path / 'missing.npy'}"],
                                tmp_path))


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        lnf.load(tmp_path / "missing.ckpt")
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable torch checkpoint"):
        lnf.load(bad)


def test_a_run_without_a_logger_trains_and_writes_its_metrics(tmp_path):
    """logger=none: the learning-rate monitor of the default callbacks (which needs a logger) is left out."""
    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "trainer.max_epochs=1", "logger=none",
                                   *TINY,
                                   # checks only metrics.json: no figures, validation rollouts or long-horizon check
                                   *METRICS_ONLY],
                         tmp_path)
    train(cfg)
    assert (Path(cfg.paths.output_dir) / "metrics.json").is_file()


@pytest.mark.parametrize("override,match", [("model.latent_dim=0", "latent_dim"), ("model.reduction_steps=0", "reduction_steps")])
def test_bad_model_config_is_a_clear_error(override, match, tmp_path):
    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "logger=none", *TINY, override], tmp_path)
    with pytest.raises(ValueError, match=match):
        train(cfg)


# NaN, inf and out-of-range numbers are refused before any work starts, naming the key: each used to fail deep
# inside (int(nan): "cannot convert float NaN to integer"), to train to a misleading hint ("lower optimizer.lr",
# every rollout "diverged at step 0 … try a smaller dt") or to train nothing (lr=0).
BAD_NUMBERS = [
    ("model.latent_dim=nan", r"model\.latent_dim must be an integer ≥ 1 \(the latent dimension d\), got nan"),
    ("model.latent_dim=2.5", r"model\.latent_dim must be an integer ≥ 1.*got 2.5"),
    ("seed=nan", r"seed must be an integer ≥ 0 and ≤ 4294967295 \(the random seed\), got nan"),
    ("seed=-1", r"seed must be an integer ≥ 0.*got -1"),
    ("integrator.tol=nan", r"integrator\.tol must be a finite number > 0 \(the tolerance of the implicit solve\), "
                           r"got nan"),
    ("integrator.substeps=inf", r"integrator\.substeps must be an integer ≥ 1.*got inf"),
    ("optimizer.weight_decay=nan", r"optimizer\.weight_decay must be a finite number ≥ 0 \(Adam's weight decay\), "
                                   r"got nan"),
    ("optimizer.lr=0", r"optimizer\.lr must be a finite number > 0 \(the learning rate of the field; 0 trains "
                       r"nothing\), got 0"),
    ("optimizer.lr=-1e-3", r"optimizer\.lr must be a finite number > 0.*got -0.001"),
    ("optimizer.lr=inf", r"optimizer\.lr must be a finite number > 0.*got inf"),
    ("optimizer.min_lr_ratio=2", r"optimizer\.min_lr_ratio must be a finite number ≥ 0 and ≤ 1.*got 2"),
    ("optimizer.warmup_steps=nan", r"optimizer\.warmup_steps must be an integer ≥ 0.*got nan"),
    ("model.w0=nan", r"model\.w0 must be a finite number > 0.*got nan"),
    ("model.step_size=0", r"model\.step_size must be a finite number > 0.*got 0"),
    ("scene.mass=nan", r"scene\.mass must be a finite number, got nan"),
    ("scene.theta0_range=[0,inf]", r"scene\.theta0_range\[1\] must be a finite number, got inf"),
    ("data.noise=nan", r"data\.noise must be a finite number, got nan"),
    ("evaluation.long_dt=nan", r"evaluation\.long_dt must be a finite number, got nan"),
    ("trainer.gradient_clip_val=nan", r"trainer\.gradient_clip_val must be a finite number, got nan"),
    ("dynamics=latent_mlp dynamics.lr=nan", r"dynamics\.lr must be a finite number > 0.*got nan"),
]


@pytest.mark.parametrize("override,match", BAD_NUMBERS, ids=[o for o, _ in BAD_NUMBERS])
def test_non_finite_and_out_of_range_settings_are_refused_before_any_work(override, match, tmp_path, monkeypatch):
    import lnf.train

    def no_data(*args, **kwargs):
        raise AssertionError("work started before the settings were checked")

    monkeypatch.setattr(lnf.train, "LNFModule", no_data)
    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "logger=none", *TINY, *override.split()],
                         tmp_path)
    with pytest.raises(ValueError, match=match):
        train(cfg)
    assert not (tmp_path / "data").exists() and not (tmp_path / "out" / "checkpoints").exists()


def test_module_refuses_a_zero_or_non_finite_learning_rate():
    """The Python API (LNFModule without lnf.train) refuses them too."""
    from lnf.training.module import LNFModule

    specs = dict(scene={"_target_": "lnf.scenes.LiftedPendulum"}, model={"width": 8, "hyper_width": 4},
                 quadrature={"_target_": "lnf.quadrature.GaussLegendre", "order": 2})
    for optimizer, match in (({"lr": 0.0}, r"optimizer\.lr must be a finite number > 0"),
                             ({"weight_decay": float("nan")}, r"optimizer\.weight_decay must be a finite number ≥ 0")):
        with pytest.raises(ValueError, match=match):
            LNFModule(optimizer=optimizer, **specs)


def test_cli_multirun_sweep(tmp_path):
    """The documented sweep command, with tiny settings, through the real CLI."""
    env = {**os.environ, "LNF_ROOT": str(tmp_path), "WANDB_MODE": "offline"}
    cmd = [sys.executable, "-m", "lnf.train", "-m", "+experiment=pendulum", "integrator=rk4,implicit_midpoint",
           "model.latent_dim=1,2", "trainer=smoke", "logger=csv", "trainer.max_epochs=1", *TINY,
           # each job's metrics are what is checked: no figures, validation rollouts or long-horizon check
           *METRICS_ONLY]
    proc = subprocess.run(cmd, cwd=Path(__file__).resolve().parents[1], env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = sorted(tmp_path.glob("outputs/pendulum/multiruns/*/*/metrics.json"))
    assert len(runs) == 4


def test_readme_python_example_runs(trained):
    """The README's Python API example, run as written against a trained checkpoint."""
    _, cfg, _ = trained
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = text.split("## Using a trained model from Python")[1].split("```python")[1].split("```")[0]
    assert '"outputs/pendulum/runs/<date>/checkpoints/last.ckpt"' in block
    block = block.replace('"outputs/pendulum/runs/<date>/checkpoints/last.ckpt"', repr(str(ckpt)))
    namespace: dict = {}
    exec(compile(block, "README example", "exec"), namespace)
    assert namespace["fields"].shape == (2, 128 * 128, 1) and namespace["traj"].q.shape == (2, 201, 1)


BASELINES = {
    "pod": ["model=pod", "model.latent_dim=2", "++model.width=16"],  # a SIREN setting POD drops with a warning
    "full_order": ["model=full_order", "model.resolution=12"],
    "latent_mlp": ["dynamics=latent_mlp", "dynamics.iterations=20", "model.width=16", "model.hyper_width=8"],
}


@pytest.mark.parametrize("name", sorted(BASELINES))
def test_each_baseline_is_trained_and_evaluated_by_the_same_entry_point(name, tmp_path):
    data = [o for o in TINY if o.startswith(("data.", "evaluation."))]
    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "logger=csv", *data, *BASELINES[name],
                                   # checks test metrics and the checkpoint: no figures, validation rollouts or
                                   # long-horizon check
                                   *METRICS_ONLY],
                         tmp_path)
    metrics = train(cfg)
    out = Path(cfg.paths.output_dir)
    saved = json.loads((out / "metrics.json").read_text())
    assert saved == pytest.approx(metrics) and np.isfinite(saved["field_rel_l2/all/median"])
    model = lnf.load(out / "checkpoints" / "last.ckpt")  # holds what was fitted after or instead of training
    assert type(model).__name__ == {"pod": "PODGalerkin", "full_order": "FullOrderModel",
                                    "latent_mlp": "LagrangianNeuralField"}[name]
    if name == "latent_mlp":
        assert bool(model.latent_dynamics.fitted) and isinstance(get_integrator(OmegaConf.to_container(cfg.integrator)), RK4)
    res = evaluate(compose_config("evaluate", [f"ckpt_path={out / 'checkpoints' / 'last.ckpt'}", "figures=0",
                                               f"integrator={'rk4' if name == 'latent_mlp' else 'implicit_midpoint'}"],
                                  tmp_path / "eval"))
    assert res["field_rel_l2/all/median"] == pytest.approx(saved["field_rel_l2/all/median"], rel=1e-3)


def test_last_checkpoint_holds_the_weights_the_run_tested(tmp_path):
    """last.ckpt is the last epoch, not the best one: lnf.evaluate of it reproduces the run's own test metrics even
    when the best epoch is an earlier one (here the best-epoch callback is told that a higher validation loss is
    better). Lightning 2.6's save_last=True copied last.ckpt only when a better epoch was saved."""
    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "trainer.max_epochs=3", "logger=csv", *TINY,
                                   "callbacks.checkpoint.mode=max",
                                   # checkpoints (by val/loss, not a rollout) and test metrics: no figures, validation
                                   # rollouts or long-horizon check
                                   *METRICS_ONLY],
                         tmp_path)
    metrics = train(cfg)
    ckpts = Path(cfg.paths.output_dir) / "checkpoints"
    best = sorted(ckpts.glob("epoch*.ckpt"))
    assert len(best) == 1 and sorted(p.name for p in ckpts.iterdir()) == [best[0].name, "last.ckpt"]
    last = torch.load(ckpts / "last.ckpt", map_location="cpu", weights_only=False)
    first = torch.load(best[0], map_location="cpu", weights_only=False)
    assert last["global_step"] > first["global_step"]
    res = evaluate(compose_config("evaluate", [f"ckpt_path={ckpts / 'last.ckpt'}", "figures=0", "max_reduction_points=64"],
                                  tmp_path / "eval"))
    for key in ("field_rel_l2/all/median", "projection_rel_l2/all/median", "latent_rmse/median"):
        assert res[key] == pytest.approx(metrics[key], rel=1e-5), key


def test_latent_dynamics_need_a_neural_field(tmp_path):
    cfg = compose_config("train", ["+experiment=pendulum", "model=pod", "dynamics=latent_mlp"], tmp_path)
    with pytest.raises(ValueError, match="needs model=lnf"):
        train(cfg)


SCENE_EXPERIMENTS = {
    "double_pendulum": [],
    "bump": [],
    "elastic": ["scene.mesh=[6,3]"],
    # no closure fit: its shooting on the exact pullback of a forced scene takes minutes; that it acts the loads is
    # tests/test_closure.py's
    "elastic_actuated": ["scene.mesh=[6,3]", "model.closure_degree=0"],
}


@pytest.mark.parametrize("experiment", sorted(SCENE_EXPERIMENTS))
def test_every_scene_experiment_trains_and_evaluates(experiment, tmp_path):
    cfg = compose_config("train", [f"+experiment={experiment}", "trainer=smoke", "logger=csv", *TINY,
                                   *SCENE_EXPERIMENTS[experiment],
                                   # checks test metrics and the checkpoint: no figures or validation rollouts (the
                                   # long-horizon check stays: each scene's run goes through it)
                                   "evaluation.figures=0", "evaluation.every_n_epochs=0"],
                         tmp_path)
    metrics = train(cfg)
    assert {"field_rel_l2/all/median", "vpt/median", "energy_rel_err/max"} <= set(metrics)
    assert metrics["train_seconds"] > 0
    model = lnf.load(Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt")
    assert model.scene.name == experiment.split("_actuated")[0] and model.latent_dim == cfg.model.latent_dim


def test_evaluate_with_tabulated_dynamics_matches_the_exact_pullback(trained, tmp_path, caplog):
    """dynamics=tabulated at evaluation: the checkpoint's training-code range boxes the table; same metrics."""
    _, cfg, _ = trained
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
    assert torch.isfinite(lnf.load(ckpt).code_low).all()  # recorded during training
    common = [f"ckpt_path={ckpt}", "integrator=rk4", "figures=0"]
    exact = evaluate(compose_config("evaluate", [*common, "dynamics=lagrangian"], tmp_path))
    table = evaluate(compose_config("evaluate", [*common, "dynamics=tabulated"], tmp_path))
    assert table["table_nodes"] >= 16 and table["table_error"] < 1e-5 and 0 <= table["table_fallback_fraction"] <= 1
    assert ("lay off the table's box" in caplog.text) == (table["table_fallback_fraction"] > TABLE_OFF_BOX_WARN)
    # a box no wider than the training codes: the test rollouts leave it (36 %), and the log says how far
    tight = evaluate(compose_config("evaluate", [*common, "dynamics=tabulated", "dynamics.margin=0"], tmp_path))
    assert tight["table_fallback_fraction"] > TABLE_OFF_BOX_WARN and "lay off the table's box" in caplog.text
    if np.isfinite(exact["field_rel_l2/all/median"]):
        assert table["field_rel_l2/all/median"] == pytest.approx(exact["field_rel_l2/all/median"], rel=1e-3, abs=1e-4)
    with pytest.raises(ValueError, match="can switch between"):
        evaluate(compose_config("evaluate", [*common, "dynamics=latent_mlp"], tmp_path))


def test_a_choice_read_off_in_horizon_errors_rolls_out_no_further_with_the_same_errors(trained):
    """EvaluationData.within_horizon (the closure's validation rollouts): the samples before the training horizon
    only, and the same in-horizon errors and divergence as the whole rollout's."""
    from experiments.scenes import snapshot_data_of
    from lnf.evaluation_pipeline import EvaluationData, EvaluationSpec, evaluate_model

    _, cfg, _ = trained
    model = lnf.load(Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt")
    whole = EvaluationData.of_split(snapshot_data_of(model).split("val"), model.scene, 2)
    cut = whole.within_horizon()
    assert len(cut.times) == int(np.sum(whole.times < whole.train_horizon)) < len(whole.times)
    assert cut.states.shape[1] == cut.true_fields.shape[1] == len(cut.times) and cut.train_horizon == whole.train_horizon
    assert cut.within_horizon() is cut
    spec = EvaluationSpec(integrator="rk4", figures=0, long_steps=0)
    with torch.no_grad():
        a, b = (evaluate_model(model, data, spec).metrics for data in (whole, cut))
    assert "field_rel_l2/extrapolation/median" in a and "field_rel_l2/extrapolation/median" not in b
    for key in ("field_rel_l2/in_horizon/median", "field_rel_l2/in_horizon/max", "diverged_count"):
        assert b[key] == pytest.approx(a[key], rel=1e-6), key


@pytest.mark.parametrize("target, match", [
    ("lnf.scenes.LiftedPendulm", r"scene\._target_=lnf\.scenes\.LiftedPendulm: module 'lnf\.scenes' .* has no "
                                 r"'LiftedPendulm'.*Did you mean 'lnf\.scenes\.LiftedPendulum'"),
    ("lnf.scens.LiftedPendulum", r"scene\._target_=lnf\.scens\.LiftedPendulum: cannot import module 'lnf\.scens' .*"
                                 r"no module named 'lnf\.scens'; did you mean 'lnf\.scenes'\?.*PYTHONPATH"),
], ids=["class", "module"])
def test_a_misspelt_scene_class_names_the_key_the_value_and_what_is_wrong(target, match, tmp_path):
    """Hydra used to say only "Error locating target" (full_key: data.scene)."""
    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "logger=none", *TINY,
                                   f"scene._target_={target}"], tmp_path)
    with pytest.raises(ValueError, match=match):
        train(cfg)


class NoPotential(lnf.scenes.Scene):
    """A user's 1-D chain that forgot potential(): it used to train its whole budget and fail at the test."""

    field_dim, bounds, energy_scale = 1, [[0.0, 1.0]], 1.0

    def params(self):
        return {}

    def density(self, points):
        return torch.ones(points.shape[:-1], dtype=points.dtype)

    def sample_initial_states(self, n, rng):
        return rng.uniform(-1, 1, size=(n, 2))

    def simulate(self, initial_states, times):
        a = initial_states[:, None, :1] * np.cos(times)[None, :, None]
        return np.concatenate([a, -initial_states[:, None, :1] * np.sin(times)[None, :, None]], axis=-1)

    def fields(self, states, points):
        mode = np.sin(np.pi * points[:, 0])[:, None]
        return states[..., 0, None, None] * mode, states[..., 1, None, None] * mode

    def true_energy_parts(self, states):
        return 0.25 * states[..., 1] ** 2, 0.25 * states[..., 0] ** 2


def test_a_scene_without_potential_is_refused_before_any_data_or_training(tmp_path):
    from omegaconf import open_dict

    from lnf.scenes.check import SceneCheckError

    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "logger=none", *TINY], tmp_path)
    with open_dict(cfg):
        cfg.scene = {"_target_": f"{NoPotential.__module__}.NoPotential"}
    with pytest.raises(SceneCheckError, match=r"scene\._target_=.*NoPotential: the scene fails check_scene(.|\n)*"
                                              r"does not define potential\(\)"):
        train(cfg)
    assert not list((tmp_path / "data").glob("*.h5")) and not (tmp_path / "out" / "checkpoints").exists()


def test_the_gradient_loss_asks_the_scene_for_field_gradients_before_any_data(tmp_path):
    from omegaconf import open_dict

    from lnf.scenes.check import SceneCheckError

    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "logger=none", *TINY,
                                   "model.gradient_weight=0.1"], tmp_path)
    with open_dict(cfg):
        cfg.scene = {"_target_": "lnf.scenes.LiftedDoublePendulum"}
    with pytest.raises(SceneCheckError, match=r"field_gradients: model\.gradient_weight=0\.1 \(the gradient loss\) "
                                              r"needs field_gradients\(\)"):
        train(cfg)
    assert not list((tmp_path / "data").glob("*.h5"))
