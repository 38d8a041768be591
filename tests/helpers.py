"""Composing configs in tests (Hydra's compose API) with tiny data and a temporary output dir."""
from __future__ import annotations

from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

CONF = str(Path(__file__).resolve().parents[1] / "conf")

TINY = ["data.n_train=3", "data.n_val=1", "data.n_test=2", "data.n_times=20", "data.train_times=10",
        "data.fine_resolution=12", "data.coarse_resolution=8", "data.batch_size=8", "model.width=16",
        "model.hyper_width=8", "evaluation.long_steps=20", "evaluation.long_trajectories=1",
        "evaluation.every_n_epochs=1", "evaluation.val_trajectories=1", "evaluation.val_resolution=8",
        "evaluation.figures=1", "evaluation.max_reduction_points=64", "quadrature.order=4"]


def compose_config(name: str, overrides: list[str], tmp_path: Path) -> DictConfig:
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(name, overrides=overrides, return_hydra_config=True)
    with open_dict(cfg):
        cfg.paths.output_dir = str(tmp_path / "out")
        cfg.paths.data_dir = str(tmp_path / "data")
        cfg.hydra.runtime.output_dir = str(tmp_path / "out")
    HydraConfig.instance().set_config(cfg)
    return cfg
