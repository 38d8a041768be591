"""What lnf.train checks before any data are generated or steps taken: the scene (its class, the parts the run
needs), the settings the test phase will need, and a resumed checkpoint against the configured scene and settings."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from lnf.model import target_class
from lnf.scenes.base import Scene
from lnf.scenes.check import SceneCheckError, check_scene
from lnf.utils import require

log = logging.getLogger("lnf.train")


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


def scene_needs(model_spec: dict[str, Any], datamodule: Any) -> dict[str, str]:
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


def check_settings(cfg: DictConfig, module: Any) -> None:
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
    require("trainer.max_epochs", max_epochs, ("int", 1, None, "the training budget"))


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
