"""Training entry point: ``python -m lnf.train +experiment=pendulum``.

``train(cfg)`` is a pure function of the composed config (tests call it through Hydra's compose API);
``main()`` only adds ``@hydra.main``.
"""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Any, Optional

import hydra
import lightning.pytorch as pl
import torch
from omegaconf import DictConfig, OmegaConf

from lnf.training.callbacks import RolloutEvaluationCallback, write_json_atomic
from lnf.training.datamodule import SnapshotDataModule
from lnf.training.module import LNFModule
from lnf.utils import check_config, print_summary, resolved_config, run_metadata

log = logging.getLogger("lnf.train")


def _container(node: Any) -> Any:
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node


def build_loggers(cfg: DictConfig, output_dir: Path) -> list[Any]:
    loggers = []
    for name, spec in (cfg.get("logger") or {}).items():
        if spec is None:
            continue
        kwargs = {}
        if "save_dir" in spec:
            Path(spec.save_dir).mkdir(parents=True, exist_ok=True)
        loggers.append(hydra.utils.instantiate(spec, **kwargs))
    return loggers


def train(cfg: DictConfig) -> dict[str, float]:
    """Generate data if needed, train, test; returns the test metrics (also written to metrics.json)."""
    check_config(cfg)
    output_dir = Path(cfg.paths.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(int(cfg.get("threads") or torch.get_num_threads()))
    pl.seed_everything(int(cfg.seed), workers=True)
    start = time.perf_counter()

    scene_spec = _container(cfg.scene)
    datamodule: SnapshotDataModule = hydra.utils.instantiate(cfg.data, scene=scene_spec, _convert_="all")
    log.info("dataset: %s", datamodule.path)
    datamodule.prepare_data()
    module = LNFModule(scene=scene_spec, model=_container(cfg.model), quadrature=_container(cfg.quadrature),
                       optimizer=_container(cfg.optimizer), data=datamodule.describe())
    evaluation = RolloutEvaluationCallback(integrator=_container(cfg.integrator), output_dir=str(output_dir),
                                           **_container(cfg.evaluation))
    callbacks = [hydra.utils.instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    trainer: pl.Trainer = hydra.utils.instantiate(cfg.trainer, callbacks=[*callbacks, evaluation],
                                                  logger=build_loggers(cfg, output_dir) or False)
    for logger in trainer.loggers:
        logger.log_hyperparams(resolved_config(cfg))
    trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
    train_seconds = time.perf_counter() - start
    trainer.test(module, datamodule=datamodule, verbose=False)

    metrics = {k: float(v) for k, v in evaluation.test_metrics.items()}
    metrics["train_seconds"] = train_seconds
    metrics["total_seconds"] = time.perf_counter() - start
    metrics["step_size"] = float(module.model.step_size.detach())
    val = trainer.callback_metrics
    for key in ("val/loss", "val/field_rel_l2/all/median"):
        if key in val:
            metrics[key] = float(val[key])
    if trainer.is_global_zero:
        write_json_atomic(output_dir / "metrics.json", metrics)
        write_json_atomic(output_dir / "run.json", run_metadata(cfg))
        print_summary(metrics, title=f"test metrics ({output_dir})")
    return metrics


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> Optional[float]:
    metrics = train(cfg)
    return metrics.get(cfg.get("optimized_metric") or "field_rel_l2/all/median")


if __name__ == "__main__":
    main()
