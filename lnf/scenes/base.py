"""What a scene is: a body B, a mass density ω0, a potential V, a full-order simulator, an energy scale."""
from __future__ import annotations

from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch
from scipy.integrate import solve_ivp
from torch import Tensor

from lnf.quadrature import Quadrature


class DiscretePotential:
    """V restricted to fields sampled at fixed quadrature points.

    Call with q (B, N, A) and, when ``needs_gradient``, G = ∇_X q (B, N, A, dim_B); returns V (B,).
    """

    needs_gradient: bool = False

    def __call__(self, q: Tensor, G: Optional[Tensor] = None) -> Tensor:  # pragma: no cover - interface
        raise NotImplementedError

    def gradient(self, q: Tensor, G: Optional[Tensor] = None) -> tuple[Tensor, Optional[Tensor]]:
        """(∂V/∂q_j (B, N, A), ∂V/∂G_j (B, N, A, dim_B) or None): derivatives w.r.t. nodal values.

        Default: exact, by torch.func (works under no_grad and inference_mode). Override with a closed
        form where one is cheap.
        """
        from torch.func import grad, vmap

        if self.needs_gradient:
            dq, dG = vmap(grad(lambda a, b: self(a[None], b[None])[0], argnums=(0, 1)))(q, G)
            return dq, dG
        return vmap(grad(lambda a: self(a[None])[0]))(q), None


class ModalKinetic:
    """Kinetic energy beyond the flat ½∫ω0‖q̇‖²: ½ aᵀ C(θ) a with θ = P q and a = P q̇ (mode projections).

    For a finite-dimensional mechanical system lifted into a field along m modes (the double pendulum),
    T(q, q̇) = ½∫ω0‖q̇‖² + ½ aᵀ (M(θ) − κ I) a, so that on the modes the metric is M(θ) and off them the
    flat κ = ω0. Subclasses give C(θ) = M(θ) − κI, its Coriolis vector and ∂T_C/∂θ in closed form.

    Attributes:
        weighted_modes: P (m, N, A), θ_i = Σ_{j,a} P_{ija} q_{ja} (quadrature weights folded in).
    """

    def __init__(self, weighted_modes: Tensor) -> None:
        self.weighted_modes = weighted_modes

    def angles(self, x: Tensor) -> Tensor:
        """θ = P x for fields x (B, N, A) → (B, m); for a jet's J (B, N, A, d) → (B, m, d) etc."""
        return torch.einsum("mna,bna...->bm...", self.weighted_modes.to(x), x)

    def matrix(self, theta: Tensor) -> Tensor:  # pragma: no cover - interface
        """C(θ) (B, m, m)."""
        raise NotImplementedError

    def coriolis(self, theta: Tensor, theta_dot: Tensor) -> Tensor:  # pragma: no cover - interface
        """(dC/dt) θ̇ − ∂T_C/∂θ (B, m): the Coriolis/centrifugal vector of T_C = ½ θ̇ᵀ C(θ) θ̇."""
        raise NotImplementedError

    def gradient(self, theta: Tensor, theta_dot: Tensor) -> Tensor:  # pragma: no cover - interface
        """∂T_C/∂θ at fixed θ̇ (B, m)."""
        raise NotImplementedError


class GeneralizedForce:
    """Non-conservative generalized forces (damping, actuation) on fields sampled at quadrature points.

    ``field_force(t, q, v, controls)`` returns the force density f (B, N, A) per unit reference volume at the
    points, so that the reduced generalized force is τ̃ = Σ_j w_j J_jᵀ f_j (B, d). `controls` (B, c) are the
    per-trajectory load parameters of :meth:`Scene.controls` (or None).
    """

    def __init__(self, weights: Tensor) -> None:
        self.weights = weights

    def field_force(self, t: float, q: Tensor, v: Tensor, controls: Optional[Tensor]) -> Tensor:  # pragma: no cover
        raise NotImplementedError


class Scene:
    """Base class of scenes. Subclasses set the attributes and implement the methods below.

    Attributes:
        name: scene name used in configs and file attributes.
        field_dim: dim_A, dimension of the configuration field's values.
        bounds: [[lo, hi], ...] of the box-shaped body B, one row per material dimension.
        energy_scale: energy used to normalise energy errors (DESIGN.md §6).
        state_names: names of the full-order state's components (for files and plots).
    """

    name: str = "scene"
    field_dim: int = 1
    bounds: list[list[float]] = [[-1.0, 1.0], [-1.0, 1.0]]
    energy_scale: float = 1.0
    state_names: tuple[str, ...] = ()

    @property
    def body_dim(self) -> int:
        return len(self.bounds)

    # -- the Lagrangian ------------------------------------------------------------------------
    def density(self, points: Tensor) -> Tensor:
        """ω0 at points (..., N, dim_B) → (..., N)."""
        raise NotImplementedError

    def potential(self, quadrature: Quadrature) -> DiscretePotential:
        raise NotImplementedError

    def kinetic_correction(self, quadrature: Quadrature) -> Optional[ModalKinetic]:
        """Kinetic energy beyond ½∫ω0‖q̇‖² (None: the flat metric is the whole kinetic energy)."""
        return None

    def generalized_force(self, quadrature: Quadrature) -> Optional[GeneralizedForce]:
        """Non-conservative forces (None: the scene is conservative)."""
        return None

    def controls(self, states: np.ndarray) -> Optional[np.ndarray]:
        """Per-trajectory load parameters (n, c) read from full-order initial states (n, S), or None."""
        return None

    def clamp_factor(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """(s, ∇s) at points (…, N, dim_B) → (…, N), (…, N, dim_B): a factor vanishing where the field is
        clamped, for a field that meets the clamp exactly (:class:`lnf.boundary.ClampedField`)."""
        raise ValueError(f"scene {self.name!r} has no clamped boundary; set model.clamp=false")

    # -- the full-order model ------------------------------------------------------------------
    def sample_initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        raise NotImplementedError

    def released_at_rest(self, amplitude: float) -> np.ndarray:
        """The full-order state (S,) released at rest with `amplitude`, in the scene's own measure of how far
        from rest it starts (an angle in rad, a tip deflection in m): the high-energy states of the stability
        study."""
        raise NotImplementedError(f"scene {self.name!r} defines no release at rest")

    def simulate(self, initial_states: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Ground-truth full-order states (n, T, S) at `times` from initial states (n, S)."""
        raise NotImplementedError

    def fields(self, states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Configuration field q and velocity field q̇ (…, N, A) of full-order states (…, S) at points (N, dim_B)."""
        raise NotImplementedError

    def field_gradients(self, states: np.ndarray, points: np.ndarray) -> np.ndarray:
        """∇_X q (…, N, A, dim_B) of full-order states (…, S) at points (N, dim_B): the target of the
        optional gradient (Sobolev) loss ``model.gradient_weight``."""
        raise ValueError(f"scene {self.name!r} gives no field gradients; set model.gradient_weight=0")

    def true_energy_parts(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(kinetic, potential) energy of full-order states (…, S) → each (…)."""
        raise NotImplementedError

    def true_energy(self, states: np.ndarray) -> np.ndarray:
        """Total energy of full-order states (…, S) → (…)."""
        kinetic, potential = self.true_energy_parts(states)
        return kinetic + potential

    # -- description ---------------------------------------------------------------------------
    def params(self) -> dict[str, Any]:
        """Constructor arguments: rebuild with ``type(scene)(**scene.params())``."""
        raise NotImplementedError

    def spec(self) -> dict[str, Any]:
        """Self-describing spec, ``{"_target_": "module.Class", **params}``."""
        cls = type(self)
        return {"_target_": f"{cls.__module__}.{cls.__qualname__}", **self.params()}

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.params().items())
        return f"{type(self).__name__}({args})"


def check_positive(**values: float) -> None:
    """Raise a ValueError naming ``scene.<key>`` unless every value is a positive finite number."""
    for key, value in values.items():
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"scene.{key} must be a positive finite number, got {value!r}")


def check_range(**ranges: Sequence[float]) -> None:
    """Raise a ValueError naming ``scene.<key>`` unless every range is [low, high] with low ≤ high."""
    for key, rng in ranges.items():
        if len(rng) != 2 or not rng[0] <= rng[1]:
            raise ValueError(f"scene.{key} must be [low, high] with low ≤ high, got {list(rng)!r}")


def solve_trajectories(rhs: Callable[[float, np.ndarray], np.ndarray], initial_states: np.ndarray,
                       times: np.ndarray, rtol: float, atol: float, what: str) -> np.ndarray:
    """Ground truth of an ODE y' = rhs(t, y) by DOP853: states (n, T, S) at `times` from initial states (n, S)."""
    initial_states = np.asarray(initial_states, dtype=np.float64)
    out = np.empty((len(initial_states), len(times), initial_states.shape[-1]))
    for i, y0 in enumerate(initial_states):
        sol = solve_ivp(rhs, (times[0], times[-1]), y0, method="DOP853", t_eval=times, rtol=rtol, atol=atol)
        if not sol.success:
            raise RuntimeError(f"{what} ground truth failed for initial state {y0}: {sol.message}")
        out[i] = sol.y.T
    return out


def as_tensor(x: np.ndarray, like: Tensor) -> Tensor:
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)
