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
    """An integrator from an instance, a name ('rk4', 'implicit_midpoint', 'dopri5') or {'name': ..., **kwargs}."""
    if isinstance(spec, Integrator):
        return spec
    kwargs: dict[str, Any] = {}
    if isinstance(spec, dict):
        kwargs = {k: v for k, v in spec.items() if k not in ("name", "_target_")}
        spec = spec.get("name", spec.get("_target_", "").rsplit(".", 1)[-1].lower())
    name = str(spec).lower()
    aliases = {"implicitmidpoint": "implicit_midpoint", "midpoint": "implicit_midpoint"}
    name = aliases.get(name, name)
    if name not in INTEGRATORS:
        raise ValueError(f"unknown integrator {spec!r}; expected one of {sorted(INTEGRATORS)}")
    accepted = inspect.signature(INTEGRATORS[name]).parameters
    unknown = sorted(k for k in kwargs if k not in accepted)
    if unknown:
        raise ValueError(f"integrator {name} takes no {', '.join('integrator.' + k for k in unknown)} (it takes "
                         f"{', '.join(sorted(accepted)) or 'no settings'}); an experiment config may have set it for "
                         f"another integrator: remove it with {' '.join('~integrator.' + k for k in unknown)}")
    return INTEGRATORS[name](**kwargs)


__all__ = ["Integrator", "FixedStepIntegrator", "RK4", "ImplicitMidpoint", "Dopri5", "Trajectory",
           "RolloutDivergedError", "INTEGRATORS", "get_integrator"]
