"""Every option of every config group composes and instantiates."""
from pathlib import Path

import hydra
import pytest
import torch
from hydra.errors import MissingConfigException
from omegaconf import OmegaConf

from helpers import CONF, TINY, compose_config
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
            assert cfg.integrator._target_.endswith("RK4")
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
    assert cfg.integrator._target_.endswith("RK4") and cfg.quadrature.resolution == 64
