"""Integrators of the reduced dynamics (one Hydra option each)."""
from __future__ import annotations

import inspect
from typing import Any

from lnf.integrators.base import FixedStepIntegrator, Integrator, RolloutDivergedError, Trajectory
from lnf.integrators.dopri5 import Dopri5
from lnf.integrators.implicit_midpoint import ImplicitMidpoint
from lnf.integrators.rk4 import RK4

INTEGRATORS: dict[str, type[Integrator]] = {"rk4": RK4, "implicit_midpoint": ImplicitMidpoint, "dopri5": Dopri5}


def get_integrator(spec: "str | Integrator | dict[str, Any]") -> Integrator:
    """An integrator from an instance, a registered name ('rk4', 'implicit_midpoint', 'dopri5': :data:`INTEGRATORS`),
    ``{'name': ..., **kwargs}``, or a config ``{'_target_': 'pkg.mod.Class', **kwargs}`` (conf/integrator/: the class
    it names, an :class:`Integrator`, built with its settings)."""
    if isinstance(spec, Integrator):
        return spec
    kwargs: dict[str, Any] = {}
    if isinstance(spec, dict) and "_target_" in spec and "name" not in spec:
        from lnf.model import target_class

        cls = target_class(spec["_target_"], key="integrator._target_")
        if not (isinstance(cls, type) and issubclass(cls, Integrator)):
            raise ValueError(f"integrator._target_={spec['_target_']}: not a subclass of lnf.integrators.Integrator")
        return _build(cls, cls.name, {k: v for k, v in spec.items() if k != "_target_"})
    if isinstance(spec, dict):
        kwargs = {k: v for k, v in spec.items() if k != "name"}
        spec = spec.get("name", "")
    name = str(spec).lower()
    aliases = {"implicitmidpoint": "implicit_midpoint", "midpoint": "implicit_midpoint"}
    name = aliases.get(name, name)
    if name not in INTEGRATORS:
        raise ValueError(f"unknown integrator {spec!r}; expected one of {sorted(INTEGRATORS)}")
    return _build(INTEGRATORS[name], name, kwargs)


def _build(cls: type[Integrator], name: str, kwargs: dict[str, Any]) -> Integrator:
    """`cls(**kwargs)`, or a ValueError naming the settings it does not take and how to remove them."""
    accepted = inspect.signature(cls).parameters
    unknown = sorted(k for k in kwargs if k not in accepted)
    if unknown:
        raise ValueError(f"integrator {name} takes no {', '.join('integrator.' + k for k in unknown)} (it takes "
                         f"{', '.join(sorted(accepted)) or 'no settings'}); an experiment config may have set it for "
                         f"another integrator: remove it with {' '.join('~integrator.' + k for k in unknown)}")
    return cls(**kwargs)


__all__ = ["Integrator", "FixedStepIntegrator", "RK4", "ImplicitMidpoint", "Dopri5", "Trajectory",
           "RolloutDivergedError", "INTEGRATORS", "get_integrator"]
