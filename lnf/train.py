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

from lnf.baselines.latent_mlp import latent_trajectories
from lnf.training.callbacks import RolloutEvaluationCallback, write_json_atomic
from lnf.training.datamodule import SnapshotDataModule
from lnf.training.module import LNFModule
from lnf.utils import check_config, print_summary, resolved_config, run_metadata

log = logging.getLogger("lnf.train")


def fit_latent_dynamics(model: Any, datamodule: SnapshotDataModule) -> dict[str, float]:
    """Fit the black-box latent dynamics to the codes of the training trajectories (after the field)."""
    points, values, velocities = (torch.as_tensor(a) for a in datamodule.observations("train"))
    model.eval()
    q, v = latent_trajectories(model, points, values, velocities)
    with torch.enable_grad():
        info = model.latent_dynamics.fit(q, v, datamodule.config.dt)
    log.info("latent dynamics fitted in %.1f s (loss %.3e)", info["latent_fit_seconds"], info["latent_fit_loss"])
    return info


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


def save_checkpoint_atomic(trainer: pl.Trainer, path: Path) -> None:
    """`trainer.save_checkpoint` to a temporary name, then renamed: a run killed while writing never leaves a
    half-written `path` (every rank calls it; rank 0 writes)."""
    tmp = path.with_name(path.name + ".tmp")
    trainer.save_checkpoint(tmp)
    if trainer.is_global_zero:
        os.replace(tmp, path)


def resolve_checkpoint(ckpt_path: Optional[str], output_dir: Path) -> Optional[str]:
    """The checkpoint to resume from: `ckpt_path` = null (when a killed run's output dir is reused, resume
    from the newest of ``checkpoints/last.ckpt`` and Lightning's SLURM ``hpc_ckpt_*.ckpt``; else start
    afresh), "last" (``checkpoints/last.ckpt``, which must exist) or a path."""
    last = output_dir / "checkpoints" / "last.ckpt"
    if ckpt_path is None:
        # Lightning's SLURM requeue (SIGUSR1) saves hpc_ckpt_<n>.ckpt in the output dir: take the newest
        found = [p for p in [last, *output_dir.glob("hpc_ckpt_*.ckpt")] if p.is_file()]
        if found:
            newest = max(found, key=lambda p: p.stat().st_mtime)
            log.info("resuming from %s (the output dir holds a checkpoint; use a new dir to start afresh)", newest)
            return str(newest)
        return None
    path = last if str(ckpt_path) == "last" else Path(str(ckpt_path))
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path={ckpt_path}: no checkpoint at {path}; expected a Lightning checkpoint "
                                f"file, or ckpt_path=last with hydra.run.dir set to the run to resume")
    return str(path)


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
    model_spec = _container(cfg.model)
    dynamics_spec = _container(cfg.get("dynamics"))
    if dynamics_spec and not str(dynamics_spec.get("_target_", "")).endswith("ReducedDynamics"):
        model_spec["dynamics"] = dynamics_spec
    module = LNFModule(scene=scene_spec, model=model_spec, quadrature=_container(cfg.quadrature),
                       optimizer=_container(cfg.optimizer), data=datamodule.describe())
    datamodule.potential_targets = getattr(module.model, "energy_weight", 0.0) > 0  # items carry V for ℓ^E
    datamodule.gradient_targets = getattr(module.model, "gradient_weight", 0.0) > 0  # items carry ∇_X q for ℓ^G
    evaluation = RolloutEvaluationCallback(integrator=_container(cfg.integrator), output_dir=str(output_dir),
                                           **_container(cfg.evaluation))
    callbacks = [hydra.utils.instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    trainer: pl.Trainer = hydra.utils.instantiate(cfg.trainer, callbacks=[*callbacks, evaluation],
                                                  logger=build_loggers(cfg, output_dir) or False)
    if trainer.is_global_zero:  # provenance first, so that a run killed later still says what it was
        write_json_atomic(output_dir / "run.json", run_metadata(cfg))
    for logger in trainer.loggers:
        logger.log_hyperparams(resolved_config(cfg))
    ckpt_path = resolve_checkpoint(cfg.get("ckpt_path"), output_dir)
    model = module.model
    fit_info: dict[str, float] = {}
    fit_metrics: dict[str, float] = {}
    if model.trainable:
        trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path)
        # the last epoch's training and validation values (losses, validation rollouts)
        fit_metrics = {k: float(v) for k, v in trainer.callback_metrics.items()
                       if k.startswith(("train/", "val/")) and not k.endswith("_step")}
    else:
        log.info("%s is fitted in closed form: no gradient training", type(model).__name__)
        points, values, _ = datamodule.observations("train")
        fit_info.update(model.fit_to_observations(torch.as_tensor(points), torch.as_tensor(values)))
    if getattr(model, "latent_dynamics", None) is not None:
        fit_info.update(fit_latent_dynamics(model, datamodule))
    train_seconds = time.perf_counter() - start
    trainer.test(module, datamodule=datamodule, verbose=False)
    # last.ckpt, which lnf.load and lnf.evaluate read, holds the weights the test evaluated: what was fitted after
    # (or instead of) training, and the steps a max_time stop took after the last validation. (After the test:
    # a model fitted in closed form is attached to the trainer only there.)
    save_checkpoint_atomic(trainer, output_dir / "checkpoints" / "last.ckpt")

    metrics = {k: float(v) for k, v in evaluation.test_metrics.items()}
    metrics["train_seconds"] = train_seconds
    metrics["total_seconds"] = time.perf_counter() - start
    metrics.update(fit_info)
    if hasattr(model, "step_size"):
        metrics["step_size"] = float(model.step_size.detach())
    metrics.update(fit_metrics)
    if trainer.is_global_zero:
        write_json_atomic(output_dir / "metrics.json", metrics)
        print_summary(metrics, title=f"test metrics ({output_dir})")
    return metrics


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> Optional[float]:
    metrics = train(cfg)
    return optimized_value(metrics, cfg.get("optimized_metric"))


def optimized_value(metrics: dict[str, float], key: Optional[str]) -> Optional[float]:
    """metrics[key] for a sweeper; a key the run did not produce is an error, not a silent None."""
    if key is None:
        return None
    if key not in metrics:
        raise KeyError(f"optimized_metric={key} is not among this run's metrics ({', '.join(sorted(metrics))}); "
                       f"validation rollout metrics need evaluation.every_n_epochs to divide trainer.max_epochs")
    return metrics[key]


if __name__ == "__main__":
    main()
