"""What ``lnf.train`` sets up between building the model and training it: the closed-form parts fitted first,
the ``model.w0=auto`` search, and the Lightning trainer with its callbacks."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import hydra
import lightning.pytorch as pl
import torch
from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint
from omegaconf import DictConfig

from lnf.dynamics_kind import dynamics_kind
from lnf.model import build_model, dropped_settings
from lnf.training.checkpoints import AtomicCheckpointIO, confine_restored_state
from lnf.training.module import LNFModule
from lnf.training.run_report import build_loggers, progress_bar
from lnf.utils import is_number
from lnf.w0_search import choose_w0, w0_for_span


def model_settings(model: dict[str, Any], dynamics: Optional[dict[str, Any]]) -> dict[str, Any]:
    """The model's settings as the run builds it: an exact-pullback `dynamics` config joins them (it is the
    model's own), and settings this model does not take are dropped, each named in a warning."""
    model = dict(model)
    if dynamics and dynamics_kind(dynamics).needs_codes:
        model["dynamics"] = dynamics
    dropped = dropped_settings(model)
    return {k: v for k, v in model.items() if k not in dropped}


def provisional_w0(w0: Any, ckpt: Optional[dict[str, Any]], bounds: Any) -> Any:
    """`w0` as the model is first built: a number stays; ``auto`` becomes the resumed checkpoint's chosen w0, or a
    span of 5 rad over the body until the search (:func:`with_chosen_w0`) replaces it."""
    if w0 != "auto":
        return w0
    saved = ((ckpt or {}).get("hyper_parameters") or {}).get("model", {}).get("w0")
    return saved if is_number(saved) else w0_for_span(bounds, 5.0)


def fit_subspace_first(module: LNFModule, datamodule: Any, resumed: bool) -> dict[str, float]:
    """Fit the closed-form part of a model that has one (``needs_fit``: the POD part of ``model.pod_subspace``) on
    the training observations, unless the run resumes (its checkpoint holds it); returns what the fit reports."""
    if not getattr(module.model, "needs_fit", False) or resumed:
        return {}
    points, values, _ = datamodule.observations("train")
    return module.model.fit_subspace(torch.as_tensor(points), torch.as_tensor(values))


def with_chosen_w0(module: LNFModule, datamodule: Any, bounds: Any, seed: int,
                   progress: bool = False) -> tuple[LNFModule, float]:
    """``model.w0=auto``: a short search on the data (:mod:`lnf.w0_search`, with a progress bar if `progress`), then
    a fresh module with the chosen w0 (and the closed-form part already fitted, shared). Returns the module and the
    w0."""
    hparams, fitted = dict(module.hparams), module.model

    def build(w0: float) -> Any:  # each candidate as training will start it (with the POD part fitted already)
        candidate = build_model(hparams["scene"], {**hparams["model"], "w0": w0}, hparams["quadrature"])
        if getattr(candidate, "needs_fit", False):
            candidate.share_fit(fitted)
        return candidate

    chosen = choose_w0(build, bounds, datamodule, lr=module.optimizer_cfg["lr"], seed=seed, progress=progress).chosen
    pl.seed_everything(seed, workers=True)
    module = LNFModule(**{**hparams, "model": {**hparams["model"], "w0": chosen}})
    if getattr(module.model, "needs_fit", False):
        module.model.share_fit(fitted)
    return module, chosen


def build_trainer(cfg: DictConfig, output_dir: Path, evaluation: pl.Callback, resumed: bool) -> pl.Trainer:
    """The trainer of ``cfg.trainer`` with the config's callbacks, a progress bar, `evaluation` and atomic
    checkpoints; with ``logger=none`` the learning-rate monitor (which needs a logger) is left out."""
    loggers = build_loggers(cfg, output_dir, resume=resumed)
    callbacks = [hydra.utils.instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    if not loggers:
        callbacks = [c for c in callbacks if not isinstance(c, LearningRateMonitor)]
    for callback in callbacks:  # a resumed checkpoint's state may name only files of the callback's own folder
        if isinstance(callback, ModelCheckpoint):
            confine_restored_state(callback)
    callbacks += progress_bar(cfg, callbacks)
    return hydra.utils.instantiate(cfg.trainer, callbacks=[*callbacks, evaluation], plugins=[AtomicCheckpointIO()],
                                   logger=loggers or False)


def optimized_value(metrics: dict[str, float], key: Optional[str]) -> Optional[float]:
    """metrics[key] for a sweeper; a key the run did not produce is an error, not a silent None."""
    if key is None:
        return None
    if key not in metrics:
        raise KeyError(f"optimized_metric={key} is not among this run's metrics ({', '.join(sorted(metrics))}); "
                       f"validation rollout metrics need evaluation.every_n_epochs to divide trainer.max_epochs")
    return metrics[key]
