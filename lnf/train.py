"""Training entry point: ``python -m lnf.train +experiment=pendulum``.

``train(cfg)`` is a pure function of the composed config (tests call it through Hydra's compose API);
``main()`` only adds ``@hydra.main``.
"""
from __future__ import annotations

import inspect
import json
import logging
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Optional

import hydra
import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint, ProgressBar, Timer
from omegaconf import DictConfig, OmegaConf

from lnf.baselines.latent_mlp import latent_trajectories
from lnf.allocator import keep_freed_memory
from lnf.config_keys import check_known_keys
from lnf.dynamics_kind import dynamics_kind
from lnf.model import build_model, dropped_settings, target_class
from lnf.run_lock import EVALUATION_RESULTS, run_folder_lock, set_aside
from lnf.scenes.base import Scene
from lnf.scenes.check import SceneCheckError, check_scene
from lnf.training.callbacks import RolloutEvaluationCallback, write_json_atomic
from lnf.training.checkpoints import AtomicCheckpointIO, confine_restored_state, resume_checkpoint
from lnf.training.console import MetricsProgressBar, quiet_console
from lnf.training.datamodule import SnapshotDataModule
from lnf.training.loggers import finish_wandb_run
from lnf.training.module import LNFModule
from lnf.utils import check_config, is_number, print_summary, resolved_config, run_metadata
from lnf.w0_search import choose_w0, w0_for_span

log = logging.getLogger("lnf.train")


def fit_latent_dynamics(model: Any, datamodule: SnapshotDataModule) -> dict[str, float]:
    """Fit the black-box latent dynamics to the codes of the training trajectories (after the field)."""
    points, values, velocities = (torch.as_tensor(a) for a in datamodule.observations("train"))
    model.eval()
    q, v = latent_trajectories(model, points, values, velocities)
    with torch.enable_grad():
        info = model.latent_dynamics.fit(q, v, datamodule.dt)
    log.info("latent dynamics fitted in %.1f s (loss %.3e)", info["latent_fit_seconds"], info["latent_fit_loss"])
    return info


def _container(node: Any) -> Any:
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node


def build_loggers(cfg: DictConfig, output_dir: Path, resume: bool = False) -> list[Any]:
    """The configured loggers; a logger that takes ``resume`` (lnf's CSVLogger) appends to its log when resuming."""
    loggers = []
    for name, spec in (cfg.get("logger") or {}).items():
        if spec is None:
            continue
        if "save_dir" in spec:
            Path(spec.save_dir).mkdir(parents=True, exist_ok=True)
        cls = hydra.utils.get_class(spec._target_)
        kwargs = {"resume": resume} if "resume" in inspect.signature(cls).parameters else {}
        loggers.append(hydra.utils.instantiate(spec, **kwargs))
    return loggers


def _differences(group: str, saved: dict[str, Any], config: dict[str, Any], keys: set[str]) -> list[str]:
    """"group.key: checkpoint …, config …" for each of `keys` where a checkpoint's spec and the config differ."""
    return [f"{group}.{k}: checkpoint {saved.get(k)!r}, config {config.get(k)!r}" for k in sorted(keys)
            if saved.get(k) != config.get(k)]


def check_resumed_scene(ckpt: dict[str, Any], path: Path, scene_spec: dict[str, Any], allow: bool) -> None:
    """A checkpoint of another scene (or other scene parameters) is refused unless ``resume_other_scene=true``:
    equal parameter shapes would let it load silently."""
    saved = (ckpt.get("hyper_parameters") or {}).get("scene")
    if saved is None or saved == scene_spec:
        return
    diffs = "; ".join(_differences("scene", saved, scene_spec, set(saved) | set(scene_spec)))
    if not allow:
        raise ValueError(f"{path} was trained on another scene ({diffs}); resume it with its own scene, start "
                         f"afresh in a new output dir, or set resume_other_scene=true to fine-tune it on this one")
    log.warning("resuming %s, trained on another scene (%s), as resume_other_scene=true asks", path, diffs)


def build_scene(spec: dict[str, Any]) -> Scene:
    """The configured scene. Its class (``scene._target_``) is resolved first, so that an error names the key, the
    value and what is wrong (no such module, a module that fails to import, no such class in it: close matches);
    the other ``scene.*`` keys are its constructor's arguments."""
    spec = dict(spec)
    target = spec.pop("_target_", None)
    cls = target_class(target, key="scene._target_")
    if not (isinstance(cls, type) and issubclass(cls, Scene)):
        raise ValueError(f"scene._target_={target}: {target} is not a subclass of lnf.scenes.Scene (got "
                         f"{cls!r}); a scene of your own subclasses it (docs/own_system.md)")
    try:
        return cls(**spec)
    except TypeError as err:
        raise TypeError(f"scene._target_={target}: {cls.__name__}(**scene) failed ({err}); the scene.* keys other "
                        f"than _target_ ({', '.join(sorted(spec)) or 'none'}) are its constructor's arguments") from err


def scene_needs(model_spec: dict[str, Any], datamodule: SnapshotDataModule) -> dict[str, str]:
    """The scene's optional parts that this run needs ({capability: what needs it}, for ``check_scene(needs=)``):
    a simulator, fields and reference energies for a dataset that lnf generates, ∇_X q for the gradient loss,
    the reference energies for the energy loss and the clamp factor for ``model.clamp``."""
    needs: dict[str, str] = {}
    if not datamodule.from_arrays:
        why = (f"the dataset {datamodule.path}, which lnf generates from the scene (or bring your own trajectories: "
               f"lnf.trajectories.write_dataset and data.path),")
        needs.update({cap: why for cap in ("simulator", "fields", "true_energies")})
    if float(model_spec.get("energy_weight") or 0) > 0 and not datamodule.from_arrays:
        needs["true_energies"] = f"model.energy_weight={model_spec['energy_weight']} (the energy loss)"
    if float(model_spec.get("gradient_weight") or 0) > 0:
        needs["field_gradients"] = f"model.gradient_weight={model_spec['gradient_weight']} (the gradient loss)"
    if model_spec.get("clamp"):
        needs["clamp"] = "model.clamp=true"
    return needs


def check_run_scene(scene: Scene, needs: dict[str, str]) -> None:
    """Run :func:`lnf.scenes.check.check_scene` with the run's `needs`: a scene that lacks a part the run needs
    (or whose parts are inconsistent) is refused before any work. An expensive reference (an FEM model) is not
    simulated here; its declarations are still checked. The global random state is left as it was."""
    state = np.random.get_state()
    with torch.random.fork_rng(devices=[]):
        report = check_scene(scene, raise_on_problem=False, needs=needs,
                             simulate=not getattr(scene, "expensive_reference", False))
    np.random.set_state(state)
    if not report.ok:
        target = f"{type(scene).__module__}.{type(scene).__qualname__}"
        raise SceneCheckError(f"scene._target_={target}: the scene fails check_scene (run before any data are "
                              f"generated or any training), fix what it lists:\n{report}")
    log.info("%s", str(report).splitlines()[0])


RESUMED_GROUPS = ("model", "quadrature", "optimizer", "data")  # settings a resumed checkpoint must share
UNCOMPARED_DATA = ("path", "on_mismatch", "explicit_path")  # where and how the file is found, not what it holds


def check_resumed_settings(ckpt: dict[str, Any], path: Path, hparams: dict[str, Any], allow: bool) -> None:
    """A checkpoint trained with other model, quadrature, optimizer or data settings is refused unless
    ``resume_other_settings=true``: its weights (and its optimizer state, whose learning rate Lightning restores
    over the configured one) would continue under settings they were not trained with, and the run's checkpoint
    and metrics would record the new settings as if they had. A setting the checkpoint does not record (written
    by an older lnf) is not compared."""
    saved = ckpt.get("hyper_parameters") or {}
    diffs = []
    for group in RESUMED_GROUPS:
        old, new = saved.get(group), hparams.get(group)
        if not isinstance(old, dict) or not isinstance(new, dict):
            continue
        skip = UNCOMPARED_DATA if group == "data" else ()
        diffs += _differences(group, old, new, set(old) - set(skip))
    if not diffs:
        return
    if not allow:
        raise ValueError(f"{path} was trained with other settings ({'; '.join(diffs)}); resume it with its own "
                         f"settings, start afresh in a new output dir (hydra.run.dir=...), or set "
                         f"resume_other_settings=true to continue its weights under these (its optimizer state, "
                         f"learning rate included, is restored as it was)")
    log.warning("resuming %s under other settings (%s), as resume_other_settings=true asks; its optimizer state, "
                "learning rate included, is restored as it was", path, "; ".join(diffs))


def check_settings(cfg: DictConfig, module: LNFModule) -> None:
    """Settings that would otherwise fail only after training: build what the test phase needs now."""
    data = cfg.get("data") or {}
    n_times, train_times = data.get("n_times"), data.get("train_times")
    if isinstance(n_times, int) and isinstance(train_times, int) and train_times >= n_times:
        raise ValueError(f"data.train_times={train_times} must be below data.n_times={n_times}: the samples after "
                         f"the training horizon are the extrapolation test; with none, its metrics would score "
                         f"trained samples")
    try:
        module.model.quadrature_rule.build_for(module.model.scene)
    except (TypeError, ValueError) as err:
        raise ValueError(f"quadrature={OmegaConf.to_container(cfg.quadrature)}: {err}") from err
    max_epochs = cfg.trainer.get("max_epochs")
    if isinstance(max_epochs, bool) or not isinstance(max_epochs, int) or max_epochs < 1:
        raise ValueError(f"trainer.max_epochs must be an integer ≥ 1 (the training budget), got {max_epochs!r}")


def training_budget(trainer: pl.Trainer, trained: bool) -> dict[str, float]:
    """Epochs and optimiser steps run, the epoch budget, and whether ``trainer.max_time`` (`stopped_by_time_limit`)
    or anything else, such as an EarlyStopping callback (`stopped_early`), ended training before the budget."""
    max_epochs = int(trainer.max_epochs or 0)
    if not trained:
        return {"epochs_run": 0.0, "max_epochs": float(max_epochs), "global_steps": 0.0, "stopped_by_time_limit": 0.0,
                "stopped_early": 0.0}
    epochs = int(trainer.fit_loop.epoch_progress.current.completed)
    timer = next((c for c in trainer.callbacks if isinstance(c, Timer)), None)
    stopped = timer is not None and epochs < max_epochs and (timer.time_remaining("train") or 0.0) <= 0
    return {"epochs_run": float(epochs), "max_epochs": float(max_epochs), "global_steps": float(trainer.global_step),
            "stopped_by_time_limit": float(stopped), "stopped_early": float(epochs < max_epochs and not stopped)}


def stop_reason(trainer: pl.Trainer) -> str:
    """What ended training before its epoch budget when no time limit did: an EarlyStopping callback (and what it
    watched), or another callback that set ``trainer.should_stop``."""
    for cb in trainer.callbacks:
        if isinstance(cb, EarlyStopping) and cb.stopped_epoch > 0:
            return f"early stopping on {cb.monitor} (EarlyStopping, patience {cb.patience})"
    return "a callback that set trainer.should_stop"


def budget_sentence(metrics: dict[str, float], max_time: Any, trained: bool, reason: str = "") -> str:
    """The end-of-run line that says in words whether the whole epoch budget ran, and if not what stopped it."""
    if not trained:
        return "training: none (the model is fitted in closed form)"
    done, total, steps = int(metrics["epochs_run"]), int(metrics["max_epochs"]), int(metrics["global_steps"])
    if metrics.get("stopped_by_time_limit"):
        return (f"training: STOPPED by the time limit trainer.max_time={max_time} after {done} of {total} epochs "
                f"({steps} steps): these results are not those of the full budget; raise or remove "
                f"trainer.max_time and resume with the same command")
    if metrics.get("stopped_early"):
        return (f"training: STOPPED early after {done} of {total} epochs ({steps} steps) by "
                f"{reason or 'a callback that set trainer.should_stop'}")
    return f"training: all {total} epochs ran ({steps} steps); no time limit stopped it"


def run_record(cfg: DictConfig, path: Path) -> dict[str, Any]:
    """run.json's contents: this run's metadata, with the metadata of the earlier runs in the same output dir
    (a resumed run) kept under ``previous_runs``, oldest first."""
    meta = {**run_metadata(cfg), "started_at": datetime.now(timezone.utc).isoformat(timespec="seconds")}
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return meta
    if isinstance(old, dict):
        meta["previous_runs"] = [*old.pop("previous_runs", []), old]
    return meta


def train(cfg: DictConfig) -> dict[str, float]:
    """Generate data if needed, train, test; returns the test metrics (also written to metrics.json). A second run
    in the same output folder while this one runs is refused (:mod:`lnf.run_lock`)."""
    with run_folder_lock(Path(cfg.paths.output_dir), "python -m lnf.train"):
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
    model_spec = _container(cfg.model)
    dynamics_spec = _container(cfg.get("dynamics"))
    if dynamics_spec and dynamics_kind(dynamics_spec).needs_codes:  # the exact pullback is the model's own
        model_spec["dynamics"] = dynamics_spec
    dropped = dropped_settings(model_spec)  # each named in a warning
    model_spec = {k: v for k, v in model_spec.items() if k not in dropped}
    check_run_scene(scene, scene_needs(model_spec, datamodule))  # before any data are generated or steps taken
    ckpt_file, ckpt = resume_checkpoint(cfg.get("ckpt_path"), output_dir)
    chosen_settings: dict[str, float] = {}
    search_w0 = model_spec.get("w0") == "auto" and ckpt is None  # a resumed run keeps the w0 its checkpoint chose
    if model_spec.get("w0") == "auto":  # the checks below run on a provisional w0, replaced after the search
        saved = ((ckpt or {}).get("hyper_parameters") or {}).get("model", {}).get("w0")
        model_spec["w0"] = saved if is_number(saved) else w0_for_span(scene.bounds, 5.0)
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
    datamodule.gradient_targets = getattr(module.model, "gradient_weight", 0.0) > 0  # items carry ∇_X q for ℓ^G
    if search_w0:  # model.w0=auto: a short search on the data (lnf/w0_search.py), then training starts afresh
        hparams, observed = dict(module.hparams), datamodule.observations("train")[:2]

        def build(w0: float) -> Any:  # each candidate as training will start it (its POD part fitted, if any)
            candidate = build_model(hparams["scene"], {**hparams["model"], "w0": w0}, hparams["quadrature"])
            if getattr(candidate, "needs_fit", False):
                candidate.fit_subspace(*map(torch.as_tensor, observed))
            return candidate

        chosen = choose_w0(build, scene.bounds, datamodule, lr=module.optimizer_cfg["lr"], seed=int(cfg.seed)).chosen
        chosen_settings["w0"] = chosen  # reported in metrics.json beside the results it gave
        pl.seed_everything(int(cfg.seed), workers=True)
        module = LNFModule(**{**hparams, "model": {**hparams["model"], "w0": chosen}})
    callbacks = [hydra.utils.instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    for callback in callbacks:  # a resumed checkpoint's state may name only files of the callback's own folder
        if isinstance(callback, ModelCheckpoint):
            confine_restored_state(callback)
    callbacks += progress_bar(cfg, callbacks)
    trainer: pl.Trainer = hydra.utils.instantiate(
        cfg.trainer, callbacks=[*callbacks, evaluation], plugins=[AtomicCheckpointIO()],
        logger=build_loggers(cfg, output_dir, resume=ckpt_file is not None) or False)
    if trainer.is_global_zero:  # provenance first, so that a run killed later still says what it was
        write_json_atomic(output_dir / "run.json", run_record(cfg, output_dir / "run.json"))
    for logger in trainer.loggers:
        logger.log_hyperparams(resolved_config(cfg))
    model = module.model
    fit_info: dict[str, float] = {}
    fit_metrics: dict[str, float] = {}
    if getattr(model, "needs_fit", False) and ckpt_file is None:  # e.g. the POD part of model.pod_subspace=true
        points, values, _ = datamodule.observations("train")
        fit_info.update(model.fit_subspace(torch.as_tensor(points), torch.as_tensor(values)))
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
    train_seconds = time.perf_counter() - start
    budget = training_budget(trainer, model.trainable)
    trainer.test(module, datamodule=datamodule, verbose=False)
    # last.ckpt, which lnf.load and lnf.evaluate read, holds the weights the test evaluated: what was fitted after
    # (or instead of) training, and the steps a max_time stop took after the last validation. (After the test:
    # a model fitted in closed form is attached to the trainer only there.) Written through AtomicCheckpointIO:
    # a temporary name in the same folder, then renamed.
    trainer.save_checkpoint(output_dir / "checkpoints" / "last.ckpt")

    metrics = {k: float(v) for k, v in evaluation.test_metrics.items()}
    metrics["train_seconds"] = train_seconds
    metrics["total_seconds"] = time.perf_counter() - start
    metrics.update(fit_info)
    metrics.update(chosen_settings)
    metrics.update(budget)
    if hasattr(model, "step_size"):
        metrics["step_size"] = float(model.step_size.detach())
    metrics.update(fit_metrics)
    if trainer.is_global_zero:
        write_json_atomic(output_dir / "metrics.json", metrics)
    evaluation.draw_figures(trainer)  # after the results are written: a figure that fails is a warning
    if trainer.is_global_zero:
        sentence = budget_sentence(metrics, cfg.trainer.get("max_time"), model.trainable, stop_reason(trainer))
        if metrics.get("stopped_by_time_limit") or metrics.get("stopped_early"):
            log.warning("%s", sentence)  # else the table's caption alone says it
        print_summary(metrics, title=f"test metrics ({output_dir})", caption=sentence)
        for line in wandb_hints(trainer):
            log.info("%s", line)
    return metrics


def progress_bar(cfg: DictConfig, callbacks: list[Any]) -> list[Any]:
    """lnf's progress bar (losses in scientific notation, no ``v_num``) unless the bar is off or one is configured."""
    if not cfg.trainer.get("enable_progress_bar", True) or any(isinstance(c, ProgressBar) for c in callbacks):
        return []
    return [MetricsProgressBar()]


def wandb_hints(trainer: pl.Trainer) -> list[str]:
    """One line per wandb run saying where it is (wandb itself is silent, see conf/logger/wandb.yaml): an offline
    run's folder and how to upload it, an online run's address."""
    lines = []
    for logger in trainer.loggers:
        if type(logger).__name__ != "WandbLogger" or getattr(logger, "_experiment", None) is None:
            continue
        run = logger.experiment
        settings = getattr(run, "settings", None)
        if getattr(settings, "_offline", False) and getattr(settings, "sync_dir", None):
            lines.append(f"wandb: offline run; upload it with `wandb sync {settings.sync_dir}`")
        elif getattr(run, "url", None):
            lines.append(f"wandb: run at {run.url}")
    return lines


@hydra.main(version_base="1.3", config_path="pkg://lnf.conf", config_name="train")
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
