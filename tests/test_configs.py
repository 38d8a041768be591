"""Every option of every config group composes and instantiates."""
from pathlib import Path

import hydra
import pytest
import torch
from hydra.errors import MissingConfigException
from omegaconf import OmegaConf

from helpers import CONF, TINY, compose_config
from lnf.integrators import RK4, get_integrator
from lnf.model import build_model

GROUPS = ["scene", "model", "dynamics", "quadrature", "integrator", "data", "optimizer", "trainer", "logger", "callbacks"]


def _options(group):
    return sorted(p.stem for p in (Path(CONF) / group).glob("*.yaml"))


@pytest.mark.parametrize("group,option", [(g, o) for g in GROUPS for o in _options(g)])
def test_every_option_composes_and_instantiates(group, option, tmp_path):
    extra = []
    if (group, option) == ("quadrature", "stored"):  # the points and weights of trajectories written from arrays
        import numpy as np

        from lnf.trajectories import Trajectories, write_dataset

        rng = np.random.default_rng(0)
        runs = Trajectories(points=rng.uniform(-1, 1, (20, 2)), times=0.1 * np.arange(3),
                            fields=rng.normal(size=(3, 3, 20)), weights=np.full(20, 0.2))  # 3 distinct runs
        path = write_dataset(tmp_path / "mine.h5", runs.select(0), runs.select(1), runs.select(2))
        extra = [f"data.path={path}"]
    cfg = compose_config("train", ["+experiment=pendulum", f"{group}={option}", *extra], tmp_path)
    node = cfg[group]
    plain = OmegaConf.to_container(node, resolve=True)
    if group == "model":
        model = build_model(OmegaConf.to_container(cfg.scene), plain, OmegaConf.to_container(cfg.quadrature))
        if option == "full_order":  # its state is the field on resolution² nodes
            assert model.latent_dim == cfg.model.resolution ** 2
        else:
            assert model.latent_dim == cfg.model.latent_dim
    elif group == "dynamics":
        model_spec = {**OmegaConf.to_container(cfg.model, resolve=True), "dynamics": plain}
        model = build_model(OmegaConf.to_container(cfg.scene), model_spec, OmegaConf.to_container(cfg.quadrature))
        assert (model.latent_dynamics is None) == (option in ("lagrangian", "tabulated"))
        assert (model.tabulation is not None) == (option == "tabulated")
        if option == "latent_mlp":  # no Hamiltonian: the option switches the integrator to RK4
            assert isinstance(get_integrator(OmegaConf.to_container(cfg.integrator)), RK4)
    elif group == "data":
        dm = hydra.utils.instantiate(node, scene=OmegaConf.to_container(cfg.scene))
        assert dm.path.parent == Path(cfg.paths.data_dir)
    elif group == "optimizer":
        assert plain["lr"] > 0
    elif group in ("logger", "callbacks"):
        for spec in node.values():
            assert hydra.utils.instantiate(spec) is not None
    elif group == "trainer":
        if node.accelerator == "gpu" and not torch.cuda.is_available():
            assert node.devices >= 1  # composes; instantiating needs a GPU
        else:
            assert hydra.utils.instantiate(node).max_epochs >= 1
    else:
        obj = hydra.utils.instantiate(node)
        if group == "quadrature" and option == "mesh":  # the elements of the scene's own mesh
            from lnf.scenes import SoftBody

            assert len(obj.build_for(SoftBody(box=(0.5, 0.15, 0.1), cells=(2, 1, 1)))) == 2 * 8
        elif group == "quadrature" and option == "mesh_nodes":  # the nodes of the scene's own mesh
            from lnf.scenes import SoftBody

            assert len(obj.build_for(SoftBody(box=(0.5, 0.15, 0.1), cells=(2, 1, 1)))) == 3 * 2 * 2
        elif group == "quadrature":
            assert len(obj.build([[-1, 1], [-1, 1]])) > 0
        assert obj is not None


def test_experiment_is_not_in_train_defaults():
    defaults = OmegaConf.load(Path(CONF) / "train.yaml").defaults
    assert not any("experiment" in str(entry) for entry in defaults)


def test_unknown_scene_or_integrator_is_a_clear_error(tmp_path):
    for override in ("scene=nonexistent", "integrator=euler"):
        with pytest.raises(MissingConfigException, match="nonexistent|euler"):
            compose_config("train", ["+experiment=pendulum", override], tmp_path)


def test_evaluate_config_composes(tmp_path):
    cfg = compose_config("evaluate", ["ckpt_path=x.ckpt", "integrator=rk4", "quadrature=uniform"], tmp_path)
    assert isinstance(get_integrator(OmegaConf.to_container(cfg.integrator)), RK4) and cfg.quadrature.resolution == 64


@pytest.mark.parametrize("override,value", [("data.dt=1e-300", "1e-300"), ("data.dt=1e300", "1e\\+300"),
                                            ("data.dt=1e-13", "1e-13"), ("data.dt=2e6", "2000000.0"),
                                            ("data.dt=0", "0"), ("data.dt=nan", "nan")])
def test_a_data_dt_no_scene_can_mean_is_refused_before_any_generation(tmp_path, monkeypatch, override, value):
    """data.dt=1e-300 used to train on trajectories that do not move, without a word; data.dt=1e300 hung in the
    generation."""
    import lnf.train

    def no_scene(*args, **kwargs):
        raise AssertionError("the scene was built (and data generated) before data.dt was checked")

    monkeypatch.setattr(lnf.train, "build_scene", no_scene)
    cfg = compose_config("train", ["+experiment=pendulum", override], tmp_path)
    with pytest.raises(ValueError, match=rf"data\.dt must be a finite number > 1e-12 and ≤ 1000000 \(the sample "
                                         rf"spacing of the generated trajectories \[s\]\), got {value}"):
        lnf.train.train(cfg)


def test_the_data_counts_are_checked_with_the_other_numbers(tmp_path):
    from lnf.utils import check_config

    check_config(compose_config("train", ["+experiment=pendulum", *TINY, "data.dt=1e-6"], tmp_path))  # in range
    with pytest.raises(ValueError, match=r"data\.n_times must be an integer ≥ 2 \(samples per trajectory\), got 1.*"
                                         r"data\.observed_fraction must be a finite number > 0 and ≤ 1 .*got 1.5"):
        check_config(compose_config("train", ["+experiment=pendulum", "data.n_times=1", "data.train_times=1",
                                              "data.observed_fraction=1.5"], tmp_path))


def test_one_checker_for_every_number_its_unit_null_and_numpy_types():
    """lnf.utils.require: the key, the range, what it is, its unit and what null means; NumPy numbers pass, bools
    and strings do not; the value comes back as an int or a float."""
    import numpy as np

    from lnf.utils import require

    rule = (">", 0, None, "the sample spacing", "s", "the data's")
    assert require("dt", None, rule) is None and require("dt", np.float32(0.05), rule) == pytest.approx(0.05)
    with pytest.raises(ValueError, match=r"^dt must be a finite number > 0 \[s\] \(the sample spacing\) or null "
                                         r"\(the data's\), got 0$"):
        require("dt", 0, rule)
    count = ("int", 1, None, "trajectories")
    assert require("n", np.int64(3), count) == 3 and type(require("n", 4.0, count)) is int
    for bad in (True, "3", 2.5, float("nan"), None):
        with pytest.raises(ValueError, match=r"^n must be an integer ≥ 1 \(trajectories\), got "):
            require("n", bad, count)
    with pytest.raises(TypeError, match="model.latent_dim must be an integer ≥ 1"):  # the rule of NUMBER_RULES
        require("model.latent_dim", 0, error=TypeError)


def test_the_evaluation_settings_have_one_schema_in_both_entry_points(tmp_path):
    """evaluation.<key> of lnf.train and <key> of lnf.evaluate are refused by the same rule, with the same words,
    before any work; EvaluationSpec refuses them on construction too."""
    from lnf.evaluation_pipeline import EvaluationSpec
    from lnf.evaluation_settings import check_settings
    from lnf.utils import EVALUATION_RULES, check_config

    for key, rule in EVALUATION_RULES.items():
        bad = rule[1] - 1
        with pytest.raises(ValueError) as train:
            check_config(compose_config("train", ["+experiment=pendulum", f"evaluation.{key}={bad}"], tmp_path))
        with pytest.raises(ValueError) as evaluate:
            check_settings(compose_config("evaluate", ["ckpt_path=x.ckpt", f"{key}={bad}"], tmp_path))
        with pytest.raises(ValueError) as spec:
            EvaluationSpec(**{key: bad})
        words = f"must be an integer ≥ {rule[1]} ({rule[3]})"
        assert f"evaluation.{key} {words}" in str(train.value) and f"evaluation.{key} {words}" in str(spec.value)
        assert str(evaluate.value).startswith(f"{key} {words}")
