"""A double pendulum lifted into a scalar field along two Legendre modes (d = 2, chaotic at high energy).

q(X, t) = u₁(X) θ₁(t) + u₂(X) θ₂(t) with orthonormal u_i (products of Legendre polynomials), θ_i = ⟨q, u_i⟩.
The double pendulum's kinetic energy has a configuration-dependent metric M(θ), so the field Lagrangian is

    L(q, q̇) = ½ κ ‖q̇‖²_{L²} + ½ aᵀ (M(θ) − κ I) a − V(θ),   θ = ⟨q, u⟩, a = ⟨q̇, u⟩,

which is exactly the double pendulum on span(u₁, u₂) and a flat metric κ off it (κ = ω0, the density).
M(θ) = [[(m₁+m₂)ℓ₁², m₂ℓ₁ℓ₂ cos Δ], [m₂ℓ₁ℓ₂ cos Δ, m₂ℓ₂²]], Δ = θ₁ − θ₂,
V(θ) = (m₁+m₂) g ℓ₁ (1 − cos θ₁) + m₂ g ℓ₂ (1 − cos θ₂).
"""
from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from lnf.quadrature import Quadrature
from lnf.scenes.base import (DiscretePotential, ModalKinetic, Scene, StabilityCases, check_positive, check_range,
                             solve_trajectories)
from lnf.scenes.pendulum import legendre_mode


# the stability study's high-energy releases (levels θ0 / π; the default theta0_range ends at π/2)
DOUBLE_PENDULUM_CASES = StabilityCases((0.5, 0.7, 0.85, 0.95, 0.99), "θ1(0) = θ2(0) = θ0, at rest: θ0 / π", 0.5,
                                       "training range |θ_i| ≤ π/2", unit=np.pi)


class DoublePendulumKinetic(ModalKinetic):
    """C(θ) = M(θ) − κ I of the double pendulum, its Coriolis vector and ∂T_C/∂θ (closed forms)."""

    def __init__(self, weighted_modes: Tensor, a11: float, a22: float, b: float, kappa: float) -> None:
        super().__init__(weighted_modes)
        self.a11, self.a22, self.b, self.kappa = a11, a22, b, kappa  # M = [[a11, b cos Δ], [b cos Δ, a22]]

    def matrix(self, theta: Tensor) -> Tensor:
        off = self.b * torch.cos(theta[:, 0] - theta[:, 1])
        row0 = torch.stack([torch.full_like(off, self.a11 - self.kappa), off], -1)
        row1 = torch.stack([off, torch.full_like(off, self.a22 - self.kappa)], -1)
        return torch.stack([row0, row1], -2)

    def coriolis(self, theta: Tensor, theta_dot: Tensor) -> Tensor:
        s = self.b * torch.sin(theta[:, 0] - theta[:, 1])
        return torch.stack([s * theta_dot[:, 1] ** 2, -s * theta_dot[:, 0] ** 2], -1)

    def gradient(self, theta: Tensor, theta_dot: Tensor) -> Tensor:
        g = -self.b * torch.sin(theta[:, 0] - theta[:, 1]) * theta_dot[:, 0] * theta_dot[:, 1]
        return torch.stack([g, -g], -1)


class DoublePendulumPotential(DiscretePotential):
    """V = k₁ (1 − cos θ₁) + k₂ (1 − cos θ₂) with θ_i = Σ_j w_j u_i(X_j) q_j (non-local)."""

    def __init__(self, weighted_modes: Tensor, k1: float, k2: float) -> None:
        self.weighted_modes = weighted_modes  # (2, N)
        self.k = torch.tensor([k1, k2], dtype=torch.float64)

    def angles(self, q: Tensor) -> Tensor:
        return torch.einsum("bn,mn->bm", q[..., 0], self.weighted_modes.to(q))

    def __call__(self, q: Tensor, G: Optional[Tensor] = None) -> Tensor:
        return ((1.0 - torch.cos(self.angles(q))) * self.k.to(q)).sum(-1)

    def gradient(self, q: Tensor, G: Optional[Tensor] = None) -> tuple[Tensor, None]:
        s = torch.sin(self.angles(q)) * self.k.to(q)  # (B, 2)
        return torch.einsum("bm,mn->bn", s, self.weighted_modes.to(q))[..., None], None


class LiftedDoublePendulum(Scene):
    """The double pendulum lifted into a scalar field on Ω = [-1, 1]² along two Legendre modes.

    Args:
        masses, lengths: (m₁, m₂) [kg], (ℓ₁, ℓ₂) [m]; gravity g [m/s²].
        theta0_range, omega0_range: both angles θ_i(0) ~ U(theta0_range) [rad], θ̇_i(0) ~ U(omega0_range) [rad/s].
        modes: Legendre degrees (n_x, n_y) of u₁ and u₂ (distinct, so the modes are orthonormal).
        rtol, atol: tolerances of the ground-truth ODE solve (DOP853).
    """

    name = "double_pendulum"
    field_dim = 1
    state_names = ("theta1", "theta2", "theta1_dot", "theta2_dot")

    def __init__(self, masses: Sequence[float] = (1.0, 1.0), lengths: Sequence[float] = (1.0, 1.0),
                 gravity: float = 9.81, theta0_range: Sequence[float] = (-np.pi / 2, np.pi / 2),
                 omega0_range: Sequence[float] = (-1.0, 1.0), modes: Sequence[Sequence[int]] = ((3, 4), (4, 3)),
                 rtol: float = 1e-11, atol: float = 1e-11) -> None:
        if len(masses) != 2 or len(lengths) != 2:
            raise ValueError(f"scene.masses and scene.lengths must have two entries, got {list(masses)!r}, "
                             f"{list(lengths)!r}")
        check_positive(gravity=gravity, **{f"masses[{i}]": m for i, m in enumerate(masses)},
                        **{f"lengths[{i}]": ell for i, ell in enumerate(lengths)})
        check_range(theta0_range=theta0_range, omega0_range=omega0_range)
        modes = [[int(n) for n in m] for m in modes]
        if len(modes) != 2 or len(modes[0]) != len(modes[1]) or modes[0] == modes[1]:
            raise ValueError(f"scene.modes must be two distinct Legendre degree tuples of equal length, got {modes!r}")
        self.masses = [float(m) for m in masses]
        self.lengths = [float(ell) for ell in lengths]
        self.gravity = float(gravity)
        self.theta0_range = [float(v) for v in theta0_range]
        self.omega0_range = [float(v) for v in omega0_range]
        self.modes = modes
        self.rtol, self.atol = float(rtol), float(atol)
        self.bounds = [[-1.0, 1.0]] * len(modes[0])
        (m1, m2), (l1, l2) = self.masses, self.lengths
        self.a11, self.a22, self.b = (m1 + m2) * l1**2, m2 * l2**2, m2 * l1 * l2
        self.k1, self.k2 = (m1 + m2) * self.gravity * l1, m2 * self.gravity * l2
        self.kappa = 0.5 * (self.a11 + self.a22)  # flat metric off the modes (any positive value would do)
        self.energy_scale = self.k1 + self.k2

    def params(self) -> dict[str, Any]:
        return dict(masses=self.masses, lengths=self.lengths, gravity=self.gravity, theta0_range=self.theta0_range,
                    omega0_range=self.omega0_range, modes=self.modes, rtol=self.rtol, atol=self.atol)

    def mode_values(self, points: np.ndarray) -> np.ndarray:
        """(2, N) values of u₁, u₂ at points (N, dim_B)."""
        return np.stack([legendre_mode(points, degrees) for degrees in self.modes])

    def _weighted_modes(self, quadrature: Quadrature) -> Tensor:
        u = torch.as_tensor(self.mode_values(quadrature.points.double().cpu().numpy()))
        return quadrature.weights[None, :] * u.to(quadrature.weights)

    def density(self, points: Tensor) -> Tensor:
        return torch.full(points.shape[:-1], self.kappa, dtype=points.dtype, device=points.device)

    def potential(self, quadrature: Quadrature) -> DoublePendulumPotential:
        return DoublePendulumPotential(self._weighted_modes(quadrature), self.k1, self.k2)

    def kinetic_correction(self, quadrature: Quadrature) -> DoublePendulumKinetic:
        return DoublePendulumKinetic(self._weighted_modes(quadrature)[..., None], self.a11, self.a22, self.b,
                                     self.kappa)

    # -- full-order model -------------------------------------------------------------------------------
    def mass_matrix(self, theta: np.ndarray) -> np.ndarray:
        """M(θ) (…, 2, 2) for θ (…, 2)."""
        off = self.b * np.cos(theta[..., 0] - theta[..., 1])
        return np.stack([np.stack([np.full_like(off, self.a11), off], -1),
                         np.stack([off, np.full_like(off, self.a22)], -1)], -2)

    def acceleration(self, theta: np.ndarray, omega: np.ndarray) -> np.ndarray:
        """θ̈ = M(θ)⁻¹ (−c(θ, θ̇) − ∇V(θ)) (…, 2)."""
        s = self.b * np.sin(theta[..., 0] - theta[..., 1])
        rhs = -np.stack([s * omega[..., 1] ** 2 + self.k1 * np.sin(theta[..., 0]),
                         -s * omega[..., 0] ** 2 + self.k2 * np.sin(theta[..., 1])], -1)
        return np.linalg.solve(self.mass_matrix(theta), rhs[..., None])[..., 0]

    def sample_initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        theta = rng.uniform(*self.theta0_range, size=(n, 2))
        omega = rng.uniform(*self.omega0_range, size=(n, 2))
        return np.concatenate([theta, omega], axis=-1)

    def released_at_rest(self, amplitude: float) -> np.ndarray:
        """Both links at θ1 = θ2 = amplitude [rad], at rest: (θ1, θ2, ω1, ω2)."""
        return np.array([float(amplitude), float(amplitude), 0.0, 0.0])

    def stability_cases(self) -> StabilityCases:
        """Both links released at rest at θ0 = π/2 (the edge of the default training range) … 0.99π."""
        return DOUBLE_PENDULUM_CASES

    def simulate(self, initial_states: np.ndarray, times: np.ndarray) -> np.ndarray:
        def rhs(_t: float, y: np.ndarray) -> np.ndarray:
            return np.concatenate([y[2:], self.acceleration(y[:2], y[2:])])

        return solve_trajectories(rhs, initial_states, times, self.rtol, self.atol, "double-pendulum")

    def fields(self, states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = self.mode_values(points)  # (2, N)
        return (states[..., 0:2] @ u)[..., None], (states[..., 2:4] @ u)[..., None]

    def true_energy_parts(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        theta, omega = states[..., :2], states[..., 2:]
        kinetic = 0.5 * np.einsum("...i,...ij,...j->...", omega, self.mass_matrix(theta), omega)
        potential = self.k1 * (1 - np.cos(theta[..., 0])) + self.k2 * (1 - np.cos(theta[..., 1]))
        return kinetic, potential
