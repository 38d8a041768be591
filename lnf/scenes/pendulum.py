"""The paper's benchmark: a pendulum lifted into a scalar field on Ω = [-1, 1]² (docs/method.md §7.1)."""
from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np
import torch
from numpy.polynomial import legendre
from torch import Tensor

from lnf.quadrature import Quadrature
from lnf.scenes.base import (DiscretePotential, Scene, StabilityCases, check_positive, check_range,
                             solve_trajectories)


# the stability study's high-energy releases (levels θ0 / π; the default theta0_range ends at π/2)
PENDULUM_CASES = StabilityCases((0.5, 0.7, 0.85, 0.95, 0.99), "θ0 / π (released at rest; 1 = separatrix)", 0.5,
                                "training range |θ0| ≤ π/2", rotation=(0.0, 7.0), unit=np.pi)


def _legendre_factors(points: np.ndarray, degrees: Sequence[int]) -> tuple[list[np.ndarray], float]:
    """P_{n_k}(X_k) per axis k (each (N,)) and ‖Π_k P_{n_k}‖_{L²([-1,1]^dim)}."""
    points = np.asarray(points, dtype=np.float64)
    factors = [legendre.Legendre.basis(int(n))(points[..., k]) for k, n in enumerate(degrees)]
    return factors, float(np.sqrt(np.prod([2.0 / (2 * int(n) + 1) for n in degrees])))


def legendre_mode(points: np.ndarray, degrees: Sequence[int]) -> np.ndarray:
    """u(X) = Π_k P_{n_k}(X_k) / ‖Π_k P_{n_k}‖_{L²([-1,1]^dim)}, so that ‖u‖_{L²} = 1. points (N, dim) → (N,)."""
    factors, norm = _legendre_factors(points, degrees)
    return np.prod(factors, axis=0) / norm


def legendre_mode_gradient(points: np.ndarray, degrees: Sequence[int]) -> np.ndarray:
    """∇_X u of :func:`legendre_mode`: points (N, dim) → (N, dim)."""
    factors, norm = _legendre_factors(points, degrees)
    points = np.asarray(points, dtype=np.float64)
    slopes = [legendre.Legendre.basis(int(n)).deriv()(points[..., k]) for k, n in enumerate(degrees)]
    columns = [np.prod([slopes[k] if j == k else factors[j] for j in range(len(degrees))], axis=0)
               for k in range(len(degrees))]
    return np.stack(columns, -1) / norm


class ProjectedCosinePotential(DiscretePotential):
    """V(q) = m g ℓ (1 − cos⟨q, u⟩) with ⟨q, u⟩ = Σ_j w_j u(X_j) q_j (non-local)."""

    needs_gradient = False

    def __init__(self, weighted_mode: Tensor, mgl: float) -> None:
        self.weighted_mode = weighted_mode  # (N,) = w_j u(X_j)
        self.mgl = mgl

    def angle(self, q: Tensor) -> Tensor:
        return torch.einsum("bn,n->b", q[..., 0], self.weighted_mode.to(q))

    def __call__(self, q: Tensor, G: Optional[Tensor] = None) -> Tensor:
        return self.mgl * (1.0 - torch.cos(self.angle(q)))

    def gradient(self, q: Tensor, G: Optional[Tensor] = None) -> tuple[Tensor, None]:
        s = self.mgl * torch.sin(self.angle(q))
        return (s[:, None] * self.weighted_mode.to(q)[None, :])[..., None], None


class LiftedPendulum(Scene):
    """q(X, t) = u(X) θ(t), L = ½ mℓ² ‖q̇‖²_{L²} − m g ℓ (1 − cos⟨q, u⟩).

    Args:
        mass, length, gravity: pendulum parameters m [kg], ℓ [m], g [m/s²].
        theta0_range: initial angle θ0 ~ U(range) [rad].
        omega0_range: initial angular velocity θ̇0 ~ U(range) [rad/s].
        degrees: Legendre degrees (n_x, n_y) of the mode u.
        rtol, atol: tolerances of the ground-truth ODE solve (DOP853).
    """

    name = "pendulum"
    field_dim = 1
    state_names = ("theta", "theta_dot")

    def __init__(
        self,
        mass: float = 1.0,
        length: float = 1.0,
        gravity: float = 9.81,
        theta0_range: Sequence[float] = (-np.pi / 2, np.pi / 2),
        omega0_range: Sequence[float] = (-1.0, 1.0),
        degrees: Sequence[int] = (3, 4),
        rtol: float = 1e-11,
        atol: float = 1e-11,
    ) -> None:
        check_positive(mass=mass, length=length, gravity=gravity)
        check_range(theta0_range=theta0_range, omega0_range=omega0_range)
        self.mass, self.length, self.gravity = float(mass), float(length), float(gravity)
        self.theta0_range = [float(v) for v in theta0_range]
        self.omega0_range = [float(v) for v in omega0_range]
        self.degrees = [int(n) for n in degrees]
        self.rtol, self.atol = float(rtol), float(atol)
        self.bounds = [[-1.0, 1.0]] * len(self.degrees)
        self.energy_scale = self.mass * self.gravity * self.length

    def params(self) -> dict[str, Any]:
        return dict(mass=self.mass, length=self.length, gravity=self.gravity, theta0_range=self.theta0_range,
                    omega0_range=self.omega0_range, degrees=self.degrees, rtol=self.rtol, atol=self.atol)

    @property
    def inertia(self) -> float:
        return self.mass * self.length**2

    def mode(self, points: np.ndarray) -> np.ndarray:
        return legendre_mode(points, self.degrees)

    def density(self, points: Tensor) -> Tensor:
        return torch.full(points.shape[:-1], self.inertia, dtype=points.dtype, device=points.device)

    def potential(self, quadrature: Quadrature) -> ProjectedCosinePotential:
        u = torch.as_tensor(self.mode(quadrature.points.double().cpu().numpy()), dtype=quadrature.weights.dtype)
        return ProjectedCosinePotential(quadrature.weights * u.to(quadrature.weights.device), self.energy_scale)

    # -- full-order model ---------------------------------------------------------------------------------
    def sample_initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        theta = rng.uniform(*self.theta0_range, size=n)
        omega = rng.uniform(*self.omega0_range, size=n)
        return np.stack([theta, omega], axis=-1)

    def released_at_rest(self, amplitude: float) -> np.ndarray:
        """(θ, ω) = (amplitude [rad], 0)."""
        return np.array([float(amplitude), 0.0])

    def stability_cases(self) -> StabilityCases:
        """Releases at rest from θ0 = π/2 (the edge of the default training range) to 0.99π, and one pendulum
        rotating above the separatrix, (θ0, θ̇0) = (0, 7 rad/s)."""
        return PENDULUM_CASES

    def simulate(self, initial_states: np.ndarray, times: np.ndarray) -> np.ndarray:
        k = self.gravity / self.length

        def rhs(_t: float, y: np.ndarray) -> np.ndarray:
            return np.array([y[1], -k * np.sin(y[0])])

        return solve_trajectories(rhs, initial_states, times, self.rtol, self.atol, self.name)

    def fields(self, states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = self.mode(points)  # (N,)
        q = states[..., 0, None] * u
        qdot = states[..., 1, None] * u
        return q[..., None], qdot[..., None]

    def field_gradients(self, states: np.ndarray, points: np.ndarray) -> np.ndarray:
        """∇_X q = θ ∇u (…, N, 1, dim) at points (N, dim)."""
        grad = legendre_mode_gradient(points, self.degrees)  # (N, dim)
        return np.asarray(states)[..., 0, None, None, None] * grad[:, None, :]

    def true_energy_parts(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        theta, omega = states[..., 0], states[..., 1]
        return 0.5 * self.inertia * omega**2, self.energy_scale * (1.0 - np.cos(theta))
