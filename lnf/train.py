"""Training entry point: ``python -m lnf.train +experiment=pendulum``.

``train(cfg)`` is a pure function of the composed config (tests call it through Hydra's compose API);
``main()`` only adds ``@hydra.main``.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Optional

import hydra
import lightning.pytorch as pl
import torch
from omegaconf import DictConfig, OmegaConf

from lnf.allocator import keep_freed_memory
from lnf.closure_choice import fit_closure
from lnf.config_keys import check_known_keys
from lnf.run_lock import EVALUATION_RESULTS, run_folder_lock, set_aside
from lnf.tempfiles import write_json_atomic
from lnf.training.callbacks import RolloutEvaluationCallback
from lnf.training.console import quiet_console
from lnf.training.signals import ended_by_sigterm
from lnf.training.run_checks import (build_scene, check_resumed_scene, check_resumed_settings, check_run_scene,
                                     check_settings, scene_needs)
from lnf.training.run_report import (budget_sentence, fit_latent_dynamics, run_record, stop_reason, training_budget,
                                     wandb_hints)
from lnf.training.run_setup import (build_trainer, fit_subspace_first, model_settings, optimized_value,
                                    provisional_w0, with_chosen_w0)
from lnf.training.checkpoints import resume_checkpoint
from lnf.training.datamodule import SnapshotDataModule
from lnf.training.loggers import finish_wandb_run
from lnf.training.module import LNFModule
from lnf.utils import check_config, print_summary, resolved_config

log = logging.getLogger("lnf.train")


def _container(node: Any) -> Any:
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node


def train(cfg: DictConfig) -> dict[str, float]:
    """Generate data if needed, train, test; returns the test metrics (also written to metrics.json). A second run
    in the same output folder while this one runs is refused (:mod:`lnf.run_lock`)."""
    with run_folder_lock(Path(cfg.paths.output_dir), "python -m lnf.train"), ended_by_sigterm():
        try:
            return _train(cfg)
        finally:
            finish_wandb_run()  # each job of a multirun logs into a wandb run of its own


def _train(cfg: DictConfig) -> dict[str, float]:
    quiet_console()
    check_known_keys(cfg, "train", "lnf.train", allowed_extra=("experiment",))
    check_config(cfg)
    output_dir = Path(cfg.paths.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(int(cfg.get("threads") or torch.get_num_threads()))
    keep_freed_memory()  # reuse freed activation buffers (lnf/allocator.py)
    pl.seed_everything(int(cfg.seed), workers=True)
    start = time.perf_counter()

    scene_spec = _container(cfg.scene)
    scene = build_scene(scene_spec)  # a wrong scene._target_ is named with what is wrong, not Hydra's generic error
    datamodule: SnapshotDataModule = hydra.utils.instantiate(cfg.data, scene=scene, _convert_="all")
    model_spec = model_settings(_container(cfg.model), _container(cfg.get("dynamics")))
    check_run_scene(scene, scene_needs(model_spec, datamodule))  # before any data are generated or steps taken
    ckpt_file, ckpt = resume_checkpoint(cfg.get("ckpt_path"), output_dir)
    chosen_settings: dict[str, float] = {}
    search_w0 = model_spec.get("w0") == "auto" and ckpt is None  # a resumed run keeps the w0 its checkpoint chose
    if "w0" in model_spec:  # the checks below run on a provisional w0 where it is auto, replaced after the search
        model_spec["w0"] = provisional_w0(model_spec["w0"], ckpt, scene.bounds)
    module = LNFModule(scene=scene_spec, model=model_spec, quadrature=_container(cfg.quadrature),
                       optimizer=_container(cfg.optimizer), data=datamodule.describe())
    check_settings(cfg, module)
    evaluation = RolloutEvaluationCallback(integrator=_container(cfg.integrator), output_dir=str(output_dir),
                                           **_container(cfg.evaluation))
    if ckpt_file is None or ckpt_file.resolve().parent not in ((output_dir / "checkpoints").resolve(),
                                                               output_dir.resolve()):
        set_aside(output_dir, EVALUATION_RESULTS)  # a fresh run: an earlier run's results here are kept, not overwritten
    if ckpt is not None:
        check_resumed_scene(ckpt, ckpt_file, module.hparams["scene"], bool(cfg.get("resume_other_scene", False)))
        check_resumed_settings(ckpt, ckpt_file, dict(module.hparams), bool(cfg.get("resume_other_settings", False)))
        del ckpt
    datamodule.prepare_data()  # generates, or verifies every split of a stored file, before the first step
    datamodule.potential_targets = getattr(module.model, "energy_weight", 0.0) > 0  # items carry V for ℓ^E
    datamodule.acceleration_targets = getattr(module.model, "dynamics_weight", 0.0) > 0  # items carry ü for ℓ^D
    datamodule.gradient_targets = getattr(module.model, "gradient_weight", 0.0) > 0  # items carry ∇_X q for ℓ^G
    fit_info = fit_subspace_first(module, datamodule, resumed=ckpt_file is not None)
    if search_w0:  # model.w0=auto: a short search on the data (lnf/w0_search.py), then training starts afresh
        module, chosen_settings["w0"] = with_chosen_w0(module, datamodule, scene.bounds, int(cfg.seed),
                                                       bool(cfg.trainer.get("enable_progress_bar", True)))
    trainer = build_trainer(cfg, output_dir, evaluation, resumed=ckpt_file is not None)
    if trainer.is_global_zero:  # provenance first, so that a run killed later still says what it was
        write_json_atomic(output_dir / "run.json", run_record(cfg, output_dir / "run.json"))
    for logger in trainer.loggers:
        logger.log_hyperparams(resolved_config(cfg))
    model = module.model
    fit_metrics: dict[str, float] = {}
    if model.trainable:
        trainer.fit(module, datamodule=datamodule, ckpt_path=str(ckpt_file) if ckpt_file else None,
                    weights_only=True)  # a resumed checkpoint is read as tensors and plain data, never unpickled
        # the last epoch's training and validation values (losses, validation rollouts); a run resumed after
        # its last epoch trains no more and reports those its checkpoint recorded
        fit_metrics = {**module.restored_fit_metrics, **module.fit_metrics()}
    else:
        log.info("%s is fitted in closed form: no gradient training", type(model).__name__)
        points, values, _ = datamodule.observations("train")
        fit_info.update(model.fit_to_observations(torch.as_tensor(points), torch.as_tensor(values)))
    if getattr(model, "latent_dynamics", None) is not None:
        fit_info.update(fit_latent_dynamics(model, datamodule))
    if model.closure is not None:  # model.closure_degree > 0: ΔṼ fitted to the training motion (lnf/closure.py)
        fit_info.update(fit_closure(model, datamodule, evaluation.spec))
    train_seconds = time.perf_counter() - start
    budget = training_budget(trainer, model.trainable)
    trainer.test(module, datamodule=datamodule, verbose=False)
    # last.ckpt, which lnf.load and lnf.evaluate read, holds the weights the test evaluated: what was fitted after
    # (or instead of) training, and the steps a max_time stop took after the last validation. (After the test:
    # a model fitted in closed form is attached to the trainer only there.) Written through AtomicCheckpointIO:
    # a temporary name in the same folder, then renamed.
    trainer.save_checkpoint(output_dir / "checkpoints" / "last.ckpt")

    metrics = {**{k: float(v) for k, v in evaluation.test_metrics.items()}, "train_seconds": train_seconds,
               "total_seconds": time.perf_counter() - start, **fit_info, **chosen_settings, **budget}
    if hasattr(model, "step_size"):
        metrics["step_size"] = float(model.step_size.detach())
    metrics.update(fit_metrics)
    evaluation.write_results(trainer, metrics)  # metrics.json, then the figures: a figure that fails is a warning
    if trainer.is_global_zero:
        sentence = budget_sentence(metrics, cfg.trainer.get("max_time"), model.trainable, stop_reason(trainer))
        if metrics.get("stopped_by_time_limit") or metrics.get("stopped_early"):
            log.warning("%s", sentence)  # else the table's caption alone says it
        print_summary(metrics, title=f"test metrics ({output_dir})", caption=sentence)
        for line in wandb_hints(trainer):
            log.info("%s", line)
    return metrics


@hydra.main(version_base="1.3", config_path="pkg://lnf.conf", config_name="train")
def main(cfg: DictConfig) -> Optional[float]:
    metrics = train(cfg)
    return optimized_value(metrics, cfg.get("optimized_metric"))


if __name__ == "__main__":
    main()
