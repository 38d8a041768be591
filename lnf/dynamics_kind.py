"""What a kind of reduced dynamics is and needs: each dynamics class declares it (``kind``), code asks.

Three kinds ship with lnf, one class each (``conf/dynamics/``):

- ``lagrangian`` (:class:`lnf.dynamics.ReducedDynamics`): the scene's Lagrangian pulled back through φ, exact.
- ``tabulated`` (:class:`lnf.tabulated.TabulatedDynamics`): the same pullback with M̃ and Ṽ read from a Chebyshev
  table on the range of the training codes (a conservative scene and a neural field's codes).
- ``learned`` (:class:`lnf.baselines.latent_mlp.LatentMLPDynamics`): a black box q̃̈ = f(q̃, q̃̇) fitted to the
  training codes after the field; no Hamiltonian, so no symplectic integrator.

A new kind declares a :class:`DynamicsKind` as the class attribute ``kind`` (docs/extending.md).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping


@dataclass(frozen=True)
class DynamicsKind:
    """name: the config option (``dynamics=<name>``); pulled_back: the pullback of the scene's Lagrangian (a
    Hamiltonian: symplectic integrators apply, the energy is the scene's); needs_codes: built on a neural field's
    training codes (a model with codes, ``model=lnf``); trained: fitted from data after the field (not switchable
    on a trained checkpoint by ``lnf.evaluate dynamics=…``)."""

    name: str
    pulled_back: bool
    needs_codes: bool
    trained: bool


LAGRANGIAN = DynamicsKind("lagrangian", pulled_back=True, needs_codes=False, trained=False)
TABULATED = DynamicsKind("tabulated", pulled_back=True, needs_codes=True, trained=False)
LEARNED = DynamicsKind("learned", pulled_back=False, needs_codes=True, trained=True)


def dynamics_kind(spec: Mapping[str, Any], key: str = "dynamics._target_") -> DynamicsKind:
    """The kind the class of a dynamics spec (``{"_target_": "pkg.mod.Class", ...}``) declares; a ValueError
    naming `key` and the class when it declares none."""
    from lnf.model import target_class

    cls = target_class(spec.get("_target_"), key=key)
    kind = getattr(cls, "kind", None)
    if not isinstance(kind, DynamicsKind):
        raise ValueError(f"{key}={spec.get('_target_')}: {cls.__name__} declares no dynamics kind (a class attribute "
                         f"`kind = lnf.dynamics_kind.DynamicsKind(...)`: what it is and what it needs)")
    return kind
