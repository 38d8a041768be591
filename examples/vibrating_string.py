"""A vibrating string, brought to lnf as a scene of your own (the worked example of docs/own_system.md).

The string X ∈ [0, L] (a 1-D body) has line density ρ, tension τ and fixed ends; its transverse displacement
q(X, t) (a scalar field) has the Lagrangian

    L = ½ ∫ ρ q̇² dX − ½ ∫ τ (∂q/∂X)² dX,

whose potential needs ∂q/∂X. The exact solution is a sum of standing waves
q = Σ_k a_k(t) sin(kπX/L) with ω_k = kπ c / L, c = √(τ/ρ). Trajectories excite the first `modes` of them.
Full-order state: (a_1..a_m, ȧ_1..ȧ_m).
"""
from __future__ import annotations

import numpy as np
import torch

from lnf.scenes import DiscretePotential, Scene


class TensionPotential(DiscretePotential):
    """V = ½ τ Σ_j w_j (∂q/∂X)_j² on a quadrature rule: q (B, N, 1), G = ∇_X q (B, N, 1, 1) → (B,)."""

    needs_gradient = True

    def __init__(self, weights: torch.Tensor, tension: float) -> None:
        self.weights, self.tension = weights, tension

    def __call__(self, q: torch.Tensor, G: torch.Tensor | None = None) -> torch.Tensor:
        return 0.5 * self.tension * torch.einsum("bn,n->b", G[..., 0, 0] ** 2, self.weights.to(G))


class VibratingString(Scene):
    """Fixed-ends string of length `length` [m], line density `density` [kg/m], tension `tension` [N]."""

    field_dim = 1
    state_names = ("a_k", "a_k_dot")

    def __init__(self, length: float = 1.0, density: float = 1.0, tension: float = 1.0, modes: int = 1,
                 amplitude: float = 0.1) -> None:
        self.length, self.rho, self.tension = float(length), float(density), float(tension)
        self.modes, self.amplitude = int(modes), float(amplitude)
        self.bounds = [[0.0, self.length]]
        self.omega = np.arange(1, self.modes + 1) * np.pi * np.sqrt(self.tension / self.rho) / self.length
        self.energy_scale = 0.25 * self.rho * self.length * (self.omega[0] * self.amplitude) ** 2  # mode 1 at a = amplitude

    def params(self) -> dict:
        return {"length": self.length, "density": self.rho, "tension": self.tension, "modes": self.modes,
                "amplitude": self.amplitude}

    def density(self, points: torch.Tensor) -> torch.Tensor:
        return torch.full(points.shape[:-1], self.rho, dtype=points.dtype, device=points.device)

    def potential(self, quadrature) -> TensionPotential:
        return TensionPotential(quadrature.weights, self.tension)

    def clamp_factor(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """s = 4 X (L − X) / L² vanishes at both ends (model.clamp=true makes φ meet them exactly)."""
        x = points[..., 0] / self.length
        return 4 * x * (1 - x), (4 * (1 - 2 * x) / self.length)[..., None]

    # -- the exact solution, as the full-order reference ------------------------------------------
    def sample_initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        scale = self.amplitude / np.arange(1, self.modes + 1)
        return np.concatenate([rng.uniform(-1, 1, (n, self.modes)) * scale,
                               rng.uniform(-1, 1, (n, self.modes)) * scale * self.omega], axis=1)

    def simulate(self, initial_states: np.ndarray, times: np.ndarray) -> np.ndarray:
        a0, v0 = initial_states[:, None, :self.modes], initial_states[:, None, self.modes:]
        wt = self.omega * times[None, :, None]
        return np.concatenate([a0 * np.cos(wt) + v0 / self.omega * np.sin(wt),
                               -a0 * self.omega * np.sin(wt) + v0 * np.cos(wt)], axis=-1)

    def _shapes(self, points: np.ndarray) -> np.ndarray:
        k = np.arange(1, self.modes + 1)
        return np.sin(np.pi * points[:, :1] * k / self.length)  # (N, m)

    def fields(self, states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        modes = self._shapes(points)
        return ((states[..., None, :self.modes] * modes).sum(-1)[..., None],
                (states[..., None, self.modes:] * modes).sum(-1)[..., None])

    def field_gradients(self, states: np.ndarray, points: np.ndarray) -> np.ndarray:
        k = np.arange(1, self.modes + 1) * np.pi / self.length
        slopes = np.cos(points[:, :1] * k) * k  # (N, m)
        return (states[..., None, :self.modes] * slopes).sum(-1)[..., None, None]

    def true_energy_parts(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        half = 0.5 * self.length / 2  # ∫ sin² = L/2
        kinetic = half * self.rho * (states[..., self.modes:] ** 2).sum(-1)
        potential = half * self.rho * ((self.omega * states[..., :self.modes]) ** 2).sum(-1)
        return kinetic, potential

    def released_at_rest(self, amplitude: float) -> np.ndarray:
        """Mode 1 released at rest with amplitude a_1 = `amplitude` [m]."""
        state = np.zeros(2 * self.modes)
        state[0] = amplitude
        return state
