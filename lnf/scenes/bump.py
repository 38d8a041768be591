"""A pendulum whose field is a Gaussian bump carried along its arc: reducible to d = 1, but only nonlinearly.

q(X, t) = exp(−‖X − c(θ(t))‖² / σ²), c(θ) = R (sin θ, −cos θ) on Ω = [-1, 1]². The field Lagrangian is

    L(q, q̇) = ½ ω0 ‖q̇‖²_{L²} − m g ℓ (1 − cos Θ(q)),   Θ(q) = atan2(m_x, −m_y),  m = ∫ X q dX,

i.e. V = m g ℓ (1 + m_y / ‖m‖): Θ is the direction of the field's first moment. On the bump manifold
(the motion is constrained to it, a holonomic constraint) ‖∂q/∂θ‖² = R² ∫ (∂_x G)² = π R² / 2 on ℝ², and
Θ = θ, so with ω0 = 2 m ℓ² / (π R²) the constrained system is exactly the pendulum θ̈ = −(g/ℓ) sin θ. On
Ω the bump's tails are cut at the boundary; with R = 0.5, σ = 0.2 the cut changes both by < 1e-3.
Its snapshots span many linear modes (the bump moves by several widths), so POD needs many modes.
"""
from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from lnf.quadrature import Quadrature
from lnf.scenes.base import DiscretePotential, check_positive
from lnf.scenes.pendulum import LiftedPendulum


class MomentAnglePotential(DiscretePotential):
    """V(q) = m g ℓ (1 + m_y / ‖m‖) with m = Σ_j w_j X_j q_j, the field's first moment (non-local)."""

    def __init__(self, weighted_points: Tensor, mgl: float) -> None:
        self.weighted_points = weighted_points  # (N, 2) = w_j X_j
        self.mgl = mgl

    def moment(self, q: Tensor) -> Tensor:
        return torch.einsum("bn,nk->bk", q[..., 0], self.weighted_points.to(q))

    def __call__(self, q: Tensor, G: Optional[Tensor] = None) -> Tensor:
        m = self.moment(q)
        return self.mgl * (1.0 + m[:, 1] / m.norm(dim=-1).clamp_min(1e-30))

    def gradient(self, q: Tensor, G: Optional[Tensor] = None) -> tuple[Tensor, None]:
        m = self.moment(q)
        r = m.norm(dim=-1, keepdim=True).clamp_min(1e-30)
        # ∂(m_y/‖m‖)/∂m = (e_y − m m_y/‖m‖²)/‖m‖
        dm = (torch.stack([torch.zeros_like(m[:, 0]), torch.ones_like(m[:, 0])], -1) - m * m[:, 1:] / r**2) / r
        return (self.mgl * torch.einsum("bk,nk->bn", dm, self.weighted_points.to(q)))[..., None], None


class BumpPendulum(LiftedPendulum):
    """The pendulum as a Gaussian bump of width σ [m] moving on a circle of radius R [m] (field on [-1, 1]²).

    Args: as :class:`LiftedPendulum` (the pendulum and its initial states), plus
        radius: R of the circle the bump's centre moves on.
        width: σ of the bump exp(−‖X − c‖²/σ²).
    """

    name = "bump"

    def __init__(self, mass: float = 1.0, length: float = 1.0, gravity: float = 9.81,
                 theta0_range: Sequence[float] = (-np.pi / 2, np.pi / 2), omega0_range: Sequence[float] = (-1.0, 1.0),
                 radius: float = 0.5, width: float = 0.2, rtol: float = 1e-11, atol: float = 1e-11) -> None:
        super().__init__(mass=mass, length=length, gravity=gravity, theta0_range=theta0_range,
                         omega0_range=omega0_range, degrees=(0, 0), rtol=rtol, atol=atol)
        check_positive(radius=radius, width=width)
        if radius + 2 * width > 1.0:
            raise ValueError(f"scene.radius + 2·scene.width must be ≤ 1 so the bump stays inside [-1, 1]², "
                             f"got {radius} + 2·{width}")
        self.radius, self.width = float(radius), float(width)
        self.omega0_density = 2.0 * self.inertia / (np.pi * self.radius**2)

    def params(self) -> dict[str, Any]:
        return dict(mass=self.mass, length=self.length, gravity=self.gravity, theta0_range=self.theta0_range,
                    omega0_range=self.omega0_range, radius=self.radius, width=self.width, rtol=self.rtol,
                    atol=self.atol)

    def centre(self, theta: np.ndarray) -> np.ndarray:
        """c(θ) (…, 2)."""
        return self.radius * np.stack([np.sin(theta), -np.cos(theta)], -1)

    def density(self, points: Tensor) -> Tensor:
        return torch.full(points.shape[:-1], self.omega0_density, dtype=points.dtype, device=points.device)

    def potential(self, quadrature: Quadrature) -> MomentAnglePotential:
        return MomentAnglePotential(quadrature.weights[:, None] * quadrature.points, self.energy_scale)

    def _bump(self, theta: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """X − c(θ) (…, N, 2) and q = exp(−‖X − c‖²/σ²) (…, N) at points (N, 2)."""
        offset = np.asarray(points) - self.centre(theta)[..., None, :]
        return offset, np.exp(-np.sum(offset**2, -1) / self.width**2)

    def fields(self, states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        theta, omega = states[..., 0], states[..., 1]
        offset, q = self._bump(theta, points)
        dc = self.radius * np.stack([np.cos(theta), np.sin(theta)], -1)  # dc/dθ
        qdot = q * 2.0 * np.einsum("...nk,...k->...n", offset, dc) / self.width**2 * omega[..., None]
        return q[..., None], qdot[..., None]

    def field_gradients(self, states: np.ndarray, points: np.ndarray) -> np.ndarray:
        """∇_X q = −2 (X − c(θ)) q / σ² (…, N, 1, 2) at points (N, 2)."""
        offset, q = self._bump(np.asarray(states)[..., 0], points)
        return (-2.0 / self.width**2 * offset * q[..., None])[..., None, :]
