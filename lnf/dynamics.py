"""Reduced Lagrangian dynamics M̃ q̃̈ + c̃ + g̃ = 0 pulled back through φ (docs/method.md §5).

Every term is a quadrature sum over fixed points X_j with weights w_j; φ, J = ∂φ/∂q̃ and H = ∂²φ/∂q̃²
(and ∇_X φ with its q̃-derivative when the potential depends on the field gradient) come from one
batched forward-mode pass of the SIREN. Shapes: q̃, q̃̇ (B, d).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from lnf.dynamics_kind import LAGRANGIAN
from lnf.quadrature import Quadrature
from lnf.reduction import solve_mass
from lnf.scenes.base import Scene
from lnf.siren import FieldJet

# φ evaluated at (codes, points) with its derivatives: anything with the signature of ModulatedSiren.jet
JetFn = Callable[..., FieldJet]


@dataclass
class DynamicsTerms:
    """M̃ (B, d, d), c̃ (B, d), g̃ (B, d), Ṽ (B,), ∂T̃/∂q̃ (B, d), τ̃ (B, d) or None at the evaluated state."""

    mass: Tensor
    coriolis: Tensor
    gravity: Tensor
    potential: Tensor
    kinetic_gradient: Tensor
    force: Optional[Tensor] = None


class ReducedDynamics:
    """The pulled-back mechanical system of a field φ and a scene's Lagrangian on a quadrature rule.

    Args:
        jet: φ's jet function, e.g. ``ModulatedSiren.jet`` or ``LinearEmbedding.jet``.
        scene: gives ω0 and V.
        quadrature: points and weights of the integrals.

    The scene may add a kinetic energy beyond the flat ½∫ω0‖q̇‖² (:class:`lnf.scenes.base.ModalKinetic`) and
    non-conservative forces f (B, N, A), which enter as τ̃ = Σ_j w_j J_jᵀ f_j; set `controls` (B, c) to the
    trajectories' load parameters before integrating a forced scene.
    """

    kind = LAGRANGIAN

    def __init__(self, jet: JetFn, scene: Scene, quadrature: Quadrature) -> None:
        self.jet = jet
        self.scene = scene
        self.quadrature = quadrature
        self.points = quadrature.points
        self.density_weights = quadrature.weights * scene.density(quadrature.points)  # w_j ω0_j (N,)
        self.potential_fn = scene.potential(quadrature)
        self.modal = scene.kinetic_correction(quadrature)  # kinetic energy beyond the flat metric, or None
        self.force_fn = scene.generalized_force(quadrature)  # damping / actuation, or None
        self.controls: Optional[Tensor] = None  # per-trajectory load parameters (B, c) for force_fn

    # -- pieces shared by the Lagrangian and Hamiltonian forms -------------------------------------
    def _jet(self, q: Tensor, order: int) -> FieldJet:
        return self.jet(q, self.points, order=order, spatial=self.potential_fn.needs_gradient)

    def _mass(self, jet: FieldJet) -> Tensor:
        """M̃ = Σ_j w_j ω0_j J_jᵀ J_j (+ J̄ᵀ C(θ) J̄ with θ = Pφ, J̄ = PJ for a modal kinetic energy) (B, d, d)."""
        J = jet.J
        mass = torch.einsum("n,bnai,bnaj->bij", self.density_weights.to(J), J, J)
        if self.modal is not None:
            Jbar = self.modal.angles(J)
            mass = mass + torch.einsum("bmi,bmk,bkj->bij", Jbar, self.modal.matrix(self.modal.angles(jet.value)), Jbar)
        return mass

    def _force(self, t: float, jet: FieldJet, v: Tensor) -> Tensor:
        """τ̃ = Σ_j w_j J_jᵀ f_j of the scene's non-conservative force density f (B, d)."""
        Jv = torch.einsum("bnai,bi->bna", jet.J, v)
        f = self.force_fn.field_force(t, jet.value, Jv, self.controls)
        return torch.einsum("n,bna,bnai->bi", self.force_fn.weights.to(v), f, jet.J)

    def _gravity(self, jet: FieldJet) -> Tensor:
        """g̃ = ∂Ṽ/∂q̃ = Σ_j (∂V/∂q_j) J_j + (∂V/∂G_j) : ∂G_j/∂q̃ (eq. 11) (B, d)."""
        dVdq, dVdG = self.potential_fn.gradient(jet.value, jet.G)
        gravity = torch.einsum("bna,bnai->bi", dVdq, jet.J)
        if dVdG is not None:
            gravity = gravity + torch.einsum("bnak,bnaki->bi", dVdG, jet.GJ)
        return gravity

    def _velocity_contractions(self, jet: FieldJet, v: Tensor) -> tuple[Tensor, Tensor]:
        """(∂T̃/∂q̃ at fixed q̃̇, c̃ = Σ w ω0 Jᵀ H[q̃̇, q̃̇]), each (B, d)."""
        ww = self.density_weights.to(v)
        Jv = torch.einsum("bnai,bi->bna", jet.J, v)
        Hv = torch.einsum("bnaij,bj->bnai", jet.H, v)  # (B, N, A, d)
        kinetic_gradient = torch.einsum("n,bna,bnak->bk", ww, Jv, Hv)
        coriolis = torch.einsum("n,bnai,bnaj,bj->bi", ww, jet.J, Hv, v)
        if self.modal is not None:
            # T_C = ½ (J̄v)ᵀ C(θ) (J̄v): ∂/∂q̃_k = (J̄v)ᵀ C H̄_k v + ∂T_C/∂θ · J̄_k;
            # c̃_C = J̄ᵀ (C H̄[v, v] + c_C(θ, J̄v)) (the pullback of the finite system's Coriolis vector)
            theta, Jbar, Hbar_v = self.modal.angles(jet.value), self.modal.angles(jet.J), self.modal.angles(Hv)
            C = self.modal.matrix(theta)
            theta_dot = torch.einsum("bmi,bi->bm", Jbar, v)
            C_theta_dot = torch.einsum("bmk,bk->bm", C, theta_dot)
            kinetic_gradient = kinetic_gradient + torch.einsum("bm,bmk->bk", C_theta_dot, Hbar_v) \
                + torch.einsum("bm,bmk->bk", self.modal.gradient(theta, theta_dot), Jbar)
            theta_acc = torch.einsum("bmk,bk->bm", Hbar_v, v)
            inner = torch.einsum("bmk,bk->bm", C, theta_acc) + self.modal.coriolis(theta, theta_dot)
            coriolis = coriolis + torch.einsum("bmi,bm->bi", Jbar, inner)
        return kinetic_gradient, coriolis

    # -- public ------------------------------------------------------------------------------------
    def terms(self, q: Tensor, v: Tensor, t: float = 0.0) -> DynamicsTerms:
        jet = self._jet(q, order=2)
        kinetic_gradient, coriolis = self._velocity_contractions(jet, v)
        potential = self.potential_fn(jet.value, jet.G)
        force = self._force(t, jet, v) if self.force_fn is not None else None
        return DynamicsTerms(self._mass(jet), coriolis, self._gravity(jet), potential, kinetic_gradient, force)

    def static_terms(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(M̃ (B, d, d), Ṽ (B,), g̃ (B, d)): the velocity-free terms, from one first-order jet (no H)."""
        jet = self._jet(q, order=1)
        return self._mass(jet), self.potential_fn(jet.value, jet.G), self._gravity(jet)

    def static_terms_with_mass_slope(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(M̃, Ṽ, g̃) as :meth:`static_terms` and ∂M̃/∂q̃ (B, k, d, d), [:, k] = ∂M̃/∂q̃_k. The flat kinetic energy's
        slope comes from the same second-order jet, ∂M̃_ij/∂q̃_k = Σ_n w_n ω0_n (H_nik·J_nj + J_ni·H_njk); with a
        modal kinetic energy M̃ is differentiated in forward mode instead."""
        if self.modal is not None:
            from torch.func import jvp

            eye = torch.eye(q.shape[-1], dtype=q.dtype, device=q.device)
            with torch.enable_grad():
                slope = torch.stack([jvp(self.mass_matrix, (q,), (eye[k].expand_as(q),))[1]
                                     for k in range(q.shape[-1])], 1)
            return (*self.static_terms(q), slope)
        jet = self._jet(q, order=2)
        half = torch.einsum("n,bnaik,bnaj->bkij", self.density_weights.to(jet.J), jet.H, jet.J)
        return (self._mass(jet), self.potential_fn(jet.value, jet.G), self._gravity(jet),
                half + half.transpose(-1, -2))

    def acceleration(self, q: Tensor, v: Tensor, t: float = 0.0, extra_force: Optional[Tensor] = None) -> Tensor:
        """q̃̈ = M̃⁻¹ (−c̃ − g̃ + τ̃ [+ `extra_force` (B, d), e.g. a closure's −∇ΔṼ]) (B, d)."""
        terms = self.terms(q, v, t)
        rhs = -terms.coriolis - terms.gravity
        for force in (terms.force, extra_force):
            if force is not None:
                rhs = rhs + force
        return solve_mass(terms.mass, rhs)

    def hamiltonian_derivatives(self, q: Tensor, p: Tensor, t: float = 0.0) -> tuple[Tensor, Tensor]:
        """(∂H/∂p̃ = q̃̇, −∂H/∂q̃ + τ) at (q̃, p̃) for H = ½ p̃ᵀM̃⁻¹p̃ + Ṽ, from one jet evaluation."""
        jet = self._jet(q, order=2)
        v = solve_mass(self._mass(jet), p)
        kinetic_gradient, _ = self._velocity_contractions(jet, v)
        force = kinetic_gradient - self._gravity(jet)
        if self.force_fn is not None:
            force = force + self._force(t, jet, v)
        return v, force

    def separated_terms(self, q: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(D̃ (B, d, d), W (B, K), ∂W/∂q̃ (B, K, d)) of a separated force (``force_fn.separated()``, a
        :class:`lnf.scenes.base.SeparatedForce`): τ̃ = −D̃ q̃̇ + Σ_k a_k ∂W_k/∂q̃, from one first-order jet."""
        parts = self.force_fn.separated() if self.force_fn is not None else None
        if parts is None:
            raise ValueError(f"{type(self.scene).__name__}'s generalized force is not separated (GeneralizedForce."
                             "separated() gives None)")
        jet = self._jet(q, order=1)
        w = self.force_fn.weights.to(q)
        damping = torch.einsum("n,bnai,bnaj->bij", w * parts.damping.to(q), jet.J, jet.J)
        shapes = parts.shapes.to(q)
        return (damping, torch.einsum("n,kna,bna->bk", w, shapes, jet.value),
                torch.einsum("n,kna,bnai->bki", w, shapes, jet.J))

    def mass_matrix(self, q: Tensor) -> Tensor:
        return self._mass(self.jet(q, self.points, order=1))

    def momentum(self, q: Tensor, v: Tensor) -> Tensor:
        """p̃ = M̃(q̃) q̃̇ (B, d)."""
        return torch.einsum("bij,bj->bi", self.mass_matrix(q), v)

    def velocity(self, q: Tensor, p: Tensor) -> Tensor:
        """q̃̇ = M̃(q̃)⁻¹ p̃ (B, d)."""
        return solve_mass(self.mass_matrix(q), p)

    def potential_energy(self, q: Tensor) -> Tensor:
        jet = self._jet(q, order=0)
        return self.potential_fn(jet.value, jet.G)

    def energies(self, q: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """(T̃, Ṽ), each (...,) for q̃, q̃̇ (..., d)."""
        shape = q.shape[:-1]
        q2, v2 = q.reshape(-1, q.shape[-1]), v.reshape(-1, v.shape[-1])
        jet = self._jet(q2, order=1)
        Jv = torch.einsum("bnai,bi->bna", jet.J, v2)
        kinetic = 0.5 * torch.einsum("n,bna,bna->b", self.density_weights.to(q), Jv, Jv)
        if self.modal is not None:
            theta_dot = self.modal.angles(Jv)
            C = self.modal.matrix(self.modal.angles(jet.value))
            kinetic = kinetic + 0.5 * torch.einsum("bm,bmk,bk->b", theta_dot, C, theta_dot)
        potential = self.potential_fn(jet.value, jet.G)
        return kinetic.reshape(shape), potential.reshape(shape)
