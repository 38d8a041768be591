"""What a checkpoint may make lnf run: opening a file someone shared must never run code it carries.

A checkpoint is read with ``torch.load(..., weights_only=True)`` (tensors and plain containers only, no pickled
objects), and its specs' ``_target_`` classes are checked here *before* anything is imported or called:

- lnf's own extension classes (scenes, models, quadrature rules, dynamics, integrators) are always allowed;
- a class of another module is built only when the user trusts that module by name: ``lnf.load(path,
  trust=["mypkg"])``, ``python -m lnf.evaluate ... 'trust=[mypkg]'`` or ``LNF_TRUST=mypkg`` (comma-separated).
  Trusting ``mypkg`` trusts ``mypkg`` and its submodules, nothing else;
- anything else (``os.system``, a function, a module outside the trusted ones) is refused with a
  :class:`UntrustedTargetError` naming the file, the key and the value; nothing of it is imported.
"""
from __future__ import annotations

import inspect
import os
from collections.abc import Iterable, Iterator
from typing import Any

TRUST_ENV = "LNF_TRUST"


class UntrustedTargetError(ValueError):
    """A checkpoint names a ``_target_`` that lnf will not import or call; the message says how to trust it."""


class UnsafeCheckpointError(ValueError):
    """A checkpoint holds pickled Python objects beyond tensors and plain data, which lnf never unpickles."""


def trusted_modules(trust: "Iterable[str] | str | None" = None) -> tuple[str, ...]:
    """The module names the user trusts: `trust` (a name, or names) plus ``$LNF_TRUST`` (comma-separated)."""
    names = [trust] if isinstance(trust, str) else list(trust or [])
    names += os.environ.get(TRUST_ENV, "").split(",")
    out = []
    for name in names:
        name = str(name).strip()
        if not name:
            continue
        if not all(part.isidentifier() for part in name.split(".")):
            raise ValueError(f"trust: {name!r} is not a module name (expected e.g. 'mypkg' or 'mypkg.scenes')")
        out.append(name)
    return tuple(dict.fromkeys(out))


def spec_targets(tree: Any, key: str = "") -> Iterator[tuple[str, Any]]:
    """Every ``_target_`` of a nested spec, as (dotted key, value), e.g. ("scene._target_", "lnf.scenes.X")."""
    if isinstance(tree, dict):
        for k, v in tree.items():
            sub = f"{key}.{k}" if key else str(k)
            if k == "_target_":
                yield sub, v
            else:
                yield from spec_targets(v, sub)
    elif isinstance(tree, (list, tuple)):
        for i, v in enumerate(tree):
            yield from spec_targets(v, f"{key}[{i}]")


def _within(module: str, packages: Iterable[str]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in packages)


def _extension_bases() -> tuple[type, ...]:
    """The kinds of lnf class a checkpoint may name (imported here, not at module load: lnf.model imports us)."""
    from torch import nn

    from lnf.baselines.latent_mlp import LearnedLatentDynamics
    from lnf.dynamics import ReducedDynamics
    from lnf.integrators.base import Integrator
    from lnf.quadrature import QuadratureRule
    from lnf.reduced_model import ReducedModel
    from lnf.scenes.base import Scene
    from lnf.tabulated import TabulatedDynamics

    return Scene, ReducedModel, QuadratureRule, ReducedDynamics, TabulatedDynamics, LearnedLatentDynamics, \
        Integrator, nn.Module


def check_target(target: Any, key: str, source: str, trust: tuple[str, ...] = ()) -> None:
    """Refuse (:class:`UntrustedTargetError`) a ``_target_`` that is not an lnf extension class or a class of a
    trusted module. A module outside lnf is not imported unless trusted."""
    from lnf.model import target_class  # lnf's own import machinery, with its clear errors

    if not isinstance(target, str) or "." not in target or not all(p.isidentifier() for p in target.split(".")):
        raise UntrustedTargetError(f"{source}: {key} = {target!r} is not a class path of the form 'module.Class'")
    module = target.rpartition(".")[0]
    if _within(module, ("lnf",)):
        cls = target_class(target)  # importing lnf's own modules runs lnf's code only
        if inspect.isclass(cls) and _within(cls.__module__, ("lnf",)) and issubclass(cls, _extension_bases()):
            return
        raise UntrustedTargetError(
            f"{source}: {key} = {target!r} is not one of lnf's scene, model, quadrature, dynamics or integrator "
            f"classes; a checkpoint may name only those (or classes of modules you trust), so it is not loaded")
    top = module.split(".")[0]
    if not _within(module, trust):
        raise UntrustedTargetError(
            f"{source}: {key} = {target!r} names a class outside lnf, from module {module!r}, which you have not "
            f"said you trust. Opening a checkpoint imports and calls every class it names, so lnf builds only its "
            f"own classes and those of modules you name: if you know the code of {top!r} (your own scene, say), "
            f"load it with lnf.load(path, trust=[{top!r}]), python -m lnf.evaluate ... 'trust=[{top}]', or "
            f"{TRUST_ENV}={top}")
    cls = target_class(target)
    if not inspect.isclass(cls):
        raise UntrustedTargetError(f"{source}: {key} = {target!r} is a {type(cls).__name__}, not a class; a "
                                   f"checkpoint's specs name classes only, so it is not loaded")


def check_spec_targets(tree: Any, source: str, trust: "Iterable[str] | str | None" = None) -> None:
    """:func:`check_target` for every ``_target_`` of a checkpoint's specs (`source` names the file)."""
    modules = trusted_modules(trust)
    for key, target in spec_targets(tree):
        check_target(target, key, source, modules)


def read_weights_only(path: "str | os.PathLike", map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)``: tensors and plain containers, never a pickled object (unpickling
    runs code the file carries). A file that holds such objects gives an :class:`UnsafeCheckpointError` naming it
    and what it holds; any other failure (truncated, not a torch file) propagates as torch raises it."""
    import pickle

    import torch

    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:
        text = str(err)
        if "weights_only" not in text.lower() and "weights only" not in text.lower():
            raise
        what = next((line.strip() for line in text.splitlines() if "Unsupported" in line or "GLOBAL" in line),
                    text.splitlines()[0] if text else "")
        if "GLOBAL" not in text:  # not an object it refused, but bytes that are no pickle at all
            raise pickle.UnpicklingError(f"the file's contents are not a torch checkpoint ({what})") from None
        raise UnsafeCheckpointError(
            f"{path} holds pickled Python objects, not only tensors and plain data ({what}); unpickling them would "
            f"run code the file carries, so lnf does not open it. A checkpoint written by python -m lnf.train holds "
            f"none; if you made this file yourself and trust it, load it with torch.load(..., weights_only=False) "
            f"and save its tensors and plain settings again") from None
