"""A hyperelastic cantilever under gravity (the paper's target): St Venant–Kirchhoff, plane strain, 2-D.

Body B = [0, L] × [0, H], clamped at X₁ = 0, mass density ρ. The configuration field is the displacement
u: B → ℝ² (positions X + u), so `field_rel_l2` is normalised by the displacement from the reference
configuration. The Lagrangian (docs/method.md §5.1):

    T = ½ ∫ ρ ‖u̇‖² dX,   V = ∫ W(I + ∇_X u) dX + ∫ ρ g u₂ dX,   W(F) = μ E:E + ½ λ (tr E)².

Optional non-conservative forces (the paper's future work), per unit reference area:
mass-proportional Rayleigh damping −α ρ u̇ and a vertical actuation load b(X, t) = A sin(2π f t) (X₁/L) e₂
with per-trajectory amplitude A and frequency f (the scene's `controls`).

Ground truth: the Q1 finite-element model of :class:`lnf.fem.body.ElasticBody` (scikit-fem's assembly, 2 × 2
Gauss points, lumped mass) with velocity Verlet (symplectic; with damping, a conformal splitting) at a time step
below the CFL limit, or with the implicit midpoint rule (`integrator`) at any step. Initial states
(`release`), with δ ~ U(deflection_range) and a tip speed ~ U(tip_speed_range):

- ``"shape"``: the Euler–Bernoulli tip-load shape w(X₁) = δ (X₁/L)² (3 − X₁/L)/2, u₁ = −(X₂ − H/2) w', with an
  initial velocity of the same shape. It is not an equilibrium of the FEM body, so the release also excites
  its fast modes (axial, shear, higher bending), which carry a large share of the velocity.
- ``"modal"``: from the FEM's own nonlinear static equilibrium under gravity plus the load K_t δ φ₁,
  φ₁ the first bending mode about the gravity equilibrium (scaled to a unit tip deflection) and K_t the
  tangent stiffness there: the inertial load of that mode at a turning point, whose linear response is δ φ₁.
  The load is removed at t = 0; the initial velocity is the tip speed times φ₁. The fast modes stay nearly at
  rest: on 16 runs (δ ≤ 0.15 m, tip speed ≤ 0.5 m/s) 2 POD modes leave 1.6 % of the displacement and 3.2 % of
  the velocity, against 6.4 % and 64 % for ``"shape"`` (`python -m experiments.elastic_diagnostics --content`).
"""
from __future__ import annotations

import logging
import math
from typing import Any, Optional, Sequence

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from torch import Tensor

from lnf.fem.body import ElasticBody, box_mesh
from lnf.fem.materials import MATERIALS, HyperelasticMaterial, get_material
from lnf.fem.time_stepping import implicit_midpoint, verlet
from lnf.quadrature import NodeQuadrature, Quadrature
from lnf.scenes.base import (DiscretePotential, GeneralizedForce, Scene, SeparatedForce, StabilityCases, check_positive,
                             check_range)
from lnf.scenes.mesh_potential import MeshStrainPotential

log = logging.getLogger("lnf.scenes.elastic")

# the stability study's high-energy releases: tip deflections δ [m] from the default deflection_range's edge
ELASTIC_CASES = StabilityCases((0.15, 0.2, 0.25, 0.3, 0.4), "tip deflection of the release at rest δ [m]", 0.15,
                               "training range |δ| ≤ 0.15 m")


class ElasticPotential(DiscretePotential):
    """V = Σ_j w_j [W(I + G_j) + ρ g q_{j,v}] on quadrature points, v the vertical (last) axis; q (B, N, d),
    G = ∇_X q (B, N, d, d), W the material's stored energy (:mod:`lnf.fem.materials`)."""

    needs_gradient = True

    def __init__(self, weights: Tensor, material: HyperelasticMaterial, rho_g: float) -> None:
        self.weights, self.material, self.rho_g = weights, material, rho_g

    @staticmethod
    def _deformation(G: Tensor) -> Tensor:
        return G + torch.eye(G.shape[-1], dtype=G.dtype, device=G.device)

    def __call__(self, q: Tensor, G: Optional[Tensor] = None) -> Tensor:
        W = self.material.energy_density(self._deformation(G))
        w = self.weights.to(q)
        return torch.einsum("n,bn->b", w, W + self.rho_g * q[..., -1])

    def gradient(self, q: Tensor, G: Optional[Tensor] = None) -> tuple[Tensor, Tensor]:
        P = self.material.first_piola(self._deformation(G))
        w = self.weights.to(q)
        dq = torch.zeros_like(q)
        dq[..., -1] = self.rho_g * w
        return dq, w[:, None, None] * P


class CantileverLoad(GeneralizedForce):
    """f = −α ρ u̇ + A sin(2π f t) s(X) ê at quadrature points, s(X) = ((X₁ − X₁,min)/L)^p the load's profile and
    ê its direction (d,); controls (B, 2) = (A, f)."""

    def __init__(self, weights: Tensor, profile: Tensor, direction: Sequence[float], rho: float,
                 damping: float) -> None:
        super().__init__(weights)
        self.profile = profile  # (N,)
        self.direction = torch.as_tensor(list(direction), dtype=torch.float64)  # (d,)
        self.rho, self.damping = rho, damping
        shape = profile[:, None] * self.direction.to(profile)[None, :]  # (N, d)
        self._separated = SeparatedForce(torch.full_like(profile, damping * rho), shape[None], self._amplitudes)

    @staticmethod
    def _amplitudes(t: float, controls: Optional[Tensor], batch: int) -> Tensor:
        """A sin(2π f t) (B, 1) of controls (B, 2) = (A, f); zeros without controls."""
        if controls is None:
            return torch.zeros(batch, 1, dtype=torch.float64)
        return (controls[:, 0] * torch.sin(2 * math.pi * controls[:, 1] * t))[:, None]

    def separated(self) -> SeparatedForce:
        """−α ρ u̇ and one load of shape s(X) ê with amplitude A sin(2π f t) (``field_force`` reads it)."""
        return self._separated


class ElasticCantilever(Scene):
    """A 2-D St Venant–Kirchhoff cantilever under gravity, clamped at X₁ = 0 (units: m, kg, s, Pa per m depth).

    Args:
        length, height: L, H of the body B = [0, L] × [0, H].
        density: ρ; young, poisson: E, ν (plane strain); gravity: g (acts along −X₂).
        material: the stored energy, ``svk`` (St Venant–Kirchhoff) or ``neo_hookean`` (compressible).
        mesh: (nx, ny) Q1 elements of the full-order model.
        integrator: ``verlet`` (explicit, below the CFL limit) or ``implicit_midpoint`` (Newton with the exact
            tangent stiffness; any step).
        time_step: full-order step [s]; null = `cfl_fraction` × the CFL estimate.
        deflection_range, tip_speed_range: initial tip deflection δ [m] and tip speed [m/s] of the release.
        release: "shape" (Euler–Bernoulli shape) or "modal" (the FEM's equilibrium under a modal load), see above.
        damping: α [1/s] of the mass-proportional Rayleigh damping −α ρ u̇.
        load_amplitude_range, load_frequency_range: actuation A [N/m²] and f [Hz] per trajectory.
    """

    name = "elastic"
    field_dim = 2
    state_names = ("displacement", "velocity", "load")
    expensive_reference = True  # the ground truth is the Q1 FEM model itself (see Scene.expensive_reference)

    def __init__(self, length: float = 1.0, height: float = 0.4, density: float = 1.0, young: float = 200.0,
                 poisson: float = 0.3, gravity: float = 1.0, mesh: Sequence[int] = (40, 16),
                 time_step: Optional[float] = None, cfl_fraction: float = 0.5, material: str = "svk",
                 integrator: str = "verlet",
                 deflection_range: Sequence[float] = (-0.15, 0.15), tip_speed_range: Sequence[float] = (-0.5, 0.5),
                 damping: float = 0.0, load_amplitude_range: Sequence[float] = (0.0, 0.0),
                 load_frequency_range: Sequence[float] = (0.5, 1.0), release: str = "shape") -> None:
        check_positive(length=length, height=height)
        if len(mesh) != 2 or any(int(n) != n or n < 1 for n in mesh):
            raise ValueError(f"scene.mesh must be two integers (nx, ny) ≥ 1, got {list(mesh)!r}")
        self.length, self.height = float(length), float(height)
        self.mesh_shape = [int(n) for n in mesh]
        self._set_physics(density, young, poisson, gravity, damping, cfl_fraction, material, integrator, release,
                          deflection_range, tip_speed_range, load_amplitude_range, load_frequency_range)
        mesh = box_mesh([self.length, self.height], self.mesh_shape, "quad")
        self._set_body(ElasticBody(mesh, self.material, self.rho, clamped=mesh.p[0] == 0.0, intorder=2), time_step)
        self.load_direction, self.load_power = [0.0, 1.0], 1.0  # b = A sin(2π f t) (X₁/L) e₂

    def _set_physics(self, density: float, young: float, poisson: float, gravity: float, damping: float,
                     cfl_fraction: float, material: str, integrator: str, release: str,
                     deflection_range: Sequence[float], tip_speed_range: Sequence[float],
                     load_amplitude_range: Sequence[float], load_frequency_range: Sequence[float]) -> None:
        """Check and take the settings an elastic body shares with any other (material, forces, releases, time
        stepping); the body's geometry is the subclass's."""
        check_positive(density=density, young=young, cfl_fraction=cfl_fraction)
        if not 0 <= poisson < 0.5:
            raise ValueError(f"scene.poisson must be in [0, 0.5), got {poisson!r}")
        for key, value in [("gravity", gravity), ("damping", damping)]:
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"scene.{key} must be a finite number ≥ 0, got {value!r}")
        if release not in ("shape", "modal"):
            raise ValueError(f"scene.release must be 'shape' or 'modal', got {release!r}")
        if material not in MATERIALS:
            raise ValueError(f"scene.material must be one of {sorted(MATERIALS)}, got {material!r}")
        if integrator not in ("verlet", "implicit_midpoint"):
            raise ValueError(f"scene.integrator must be 'verlet' or 'implicit_midpoint', got {integrator!r}")
        check_range(deflection_range=deflection_range, tip_speed_range=tip_speed_range,
                    load_amplitude_range=load_amplitude_range, load_frequency_range=load_frequency_range)
        self.rho, self.young, self.poisson, self.gravity = float(density), float(young), float(poisson), float(gravity)
        self.damping, self.cfl_fraction = float(damping), float(cfl_fraction)
        self.deflection_range = [float(v) for v in deflection_range]
        self.tip_speed_range = [float(v) for v in tip_speed_range]
        self.load_amplitude_range = [float(v) for v in load_amplitude_range]
        self.load_frequency_range = [float(v) for v in load_frequency_range]
        self.loaded = any(v != 0 for v in self.load_amplitude_range)  # actuation present
        self.material_name, self.integrator, self.release = str(material), str(integrator), str(release)
        self.material = get_material(self.material_name, self.young, self.poisson)
        self.lam, self.mu = self.material.lam, self.material.mu

    def _set_body(self, body: ElasticBody, time_step: Optional[float]) -> None:
        """Take the full-order body: its box, clamp, tip (the nodes at the largest X₁) and stable time step."""
        self.body, self.dim = body, body.dim
        self.field_dim = body.dim
        self.bounds = body.bounds
        self.x_min = self.bounds[0][0]
        self.length = self.bounds[0][1] - self.bounds[0][0]  # along X₁, from the clamp
        self.height = self.bounds[-1][1] - self.bounds[-1][0]  # along the vertical X_d
        self.center = 0.5 * (self.bounds[-1][0] + self.bounds[-1][1])
        cfl = self.body.stable_time_step()
        self.time_step = float(time_step) if time_step is not None else float(self.cfl_fraction * cfl)
        if not (np.isfinite(self.time_step) and self.time_step > 0):
            raise ValueError(f"scene.time_step must be a positive number [s], got {time_step!r}")
        self.nodal_mass = self.body.nodal_mass  # (nn,)
        self.free_dofs = self.body.free_dofs  # unclamped nodal dofs of u.reshape(-1)
        self._tip = np.flatnonzero(np.isclose(self.body.nodes[:, 0], self.bounds[0][1]))
        self._modal: Optional[tuple[np.ndarray, np.ndarray, sp.csr_matrix]] = None  # (u_g, first mode, K_t at u_g)
        self._energy_scale: Optional[float] = None  # computed on first use (the modal one needs Newton solves)

    @property
    def energy_scale(self) -> float:
        """The energy of the largest release above the rest state [J/m]: with the "shape" release its strain
        energy (δ_max), with the "modal" one its linearised modal energy ½ δ² φ₁ᵀK_tφ₁ + ½ v² φ₁ᵀMφ₁ at the
        largest δ and tip speed v, about the gravity equilibrium (else the gravity scale ρ g |B| L)."""
        if self._energy_scale is None:
            delta = max(abs(v) for v in self.deflection_range)
            if self.release == "modal":
                _, mode, K = self.modal_reference()
                flat = mode.reshape(-1)
                stiffness = float(flat @ (K @ flat))
                speed = max(abs(v) for v in self.tip_speed_range)
                mass = float(np.repeat(self.nodal_mass, self.dim) @ flat**2)
                scale = 0.5 * delta**2 * stiffness + 0.5 * speed**2 * mass
            else:
                scale = float(self.body.strain_energy(self.beam_shape(np.array([delta])))[0])
            self._energy_scale = scale if scale > 0 else self.rho * max(self.gravity, 1.0) * self.length**2 * self.height
        return self._energy_scale

    def params(self) -> dict[str, Any]:
        return dict(length=self.length, height=self.height, density=self.rho, young=self.young,
                    poisson=self.poisson, gravity=self.gravity, mesh=self.mesh_shape,
                    time_step=self.time_step, cfl_fraction=self.cfl_fraction,
                    deflection_range=self.deflection_range, tip_speed_range=self.tip_speed_range,
                    damping=self.damping, load_amplitude_range=self.load_amplitude_range,
                    load_frequency_range=self.load_frequency_range, release=self.release,
                    material=self.material_name, integrator=self.integrator)

    # -- the Lagrangian ---------------------------------------------------------------------------------
    def density(self, points: Tensor) -> Tensor:
        return torch.full(points.shape[:-1], self.rho, dtype=points.dtype, device=points.device)

    def potential(self, quadrature: Quadrature) -> "ElasticPotential | MeshStrainPotential":
        """The continuum's V at quadrature points; on the mesh's nodes (:meth:`nodal_quadrature`), the mesh's own."""
        if isinstance(quadrature, NodeQuadrature):
            if len(quadrature) != self.body.n_nodes:
                raise ValueError(f"a NodeQuadrature of {len(quadrature)} points is not this body's mesh "
                                 f"({self.body.n_nodes} nodes): build it with scene.nodal_quadrature()")
            return MeshStrainPotential(self.body, self.rho * self.gravity)
        return ElasticPotential(quadrature.weights, self.material, self.rho * self.gravity)

    def nodal_quadrature(self) -> NodeQuadrature:
        """The full-order mesh's nodes (nn, d) [m] and lumped volumes ∫ N_a dX (nn,) [m^d]."""
        return NodeQuadrature(torch.as_tensor(self.body.nodes), torch.as_tensor(self.body.volume_per_node))

    @property
    def forced(self) -> bool:
        return self.damping > 0 or self.loaded

    @property
    def is_conservative(self) -> bool:
        """Without damping and loads the cantilever conserves its energy."""
        return not self.forced

    def generalized_force(self, quadrature: Quadrature) -> Optional[CantileverLoad]:
        if not self.forced:
            return None
        profile = ((quadrature.points[:, 0] - self.x_min) / self.length).clamp_min(0) ** self.load_power
        return CantileverLoad(quadrature.weights, profile, self.load_direction, self.rho, self.damping)

    def clamp_factor(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """s = (X₁ − X₁,min)/L (zero on the clamp) and ∇s = (1/L, 0, …), for points (…, N, d)."""
        s = (points[..., 0] - self.x_min) / self.length
        ds = torch.zeros_like(points)
        ds[..., 0] = 1.0 / self.length
        return s, ds

    def controls(self, states: np.ndarray) -> Optional[np.ndarray]:
        return np.asarray(states)[..., -2:] if self.forced else None

    def input_signals(self, controls: np.ndarray, times: np.ndarray) -> np.ndarray:
        """The actuation's amplitude A sin(2π f t) (n, T, 1) for controls (A, f) (n, 2): the load b = that × s(X) e₂."""
        controls, times = np.asarray(controls, dtype=np.float64), np.asarray(times, dtype=np.float64)
        return (controls[:, None, 0] * np.sin(2 * np.pi * controls[:, None, 1] * times[None, :]))[..., None]

    # -- the full-order model ---------------------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return self.body.n_nodes

    def release_shape(self, tip: np.ndarray) -> np.ndarray:
        """Nodal displacements (n, nn, 2) of the release with tip deflections `tip` (n,) (see `release`)."""
        if self.release == "modal":
            return self.modal_release(np.asarray(tip, dtype=np.float64))
        return self.beam_shape(tip)

    def static_equilibrium(self, nodal_load: Optional[np.ndarray] = None, start: Optional[np.ndarray] = None,
                           tol: float = 1e-10, max_iter: int = 30) -> np.ndarray:
        """Nodal displacements (nn, d) at rest under gravity and extra nodal forces (nn, d) [N] (Newton)."""
        u = np.zeros((self.n_nodes, self.dim)) if start is None else np.array(start, dtype=np.float64)
        load = np.zeros((self.n_nodes, self.dim)) if nodal_load is None else np.array(nodal_load, dtype=np.float64)
        load[:, -1] -= self.nodal_mass * self.gravity
        free = self.free_dofs
        scale = max(np.abs(load).sum(), 1e-300)
        def residual_at(u: np.ndarray) -> np.ndarray:
            return (self.body.internal_force(u[None])[0] + load).reshape(-1)[free]

        residual = residual_at(u)
        for _ in range(max_iter):
            if np.abs(residual).sum() <= tol * scale:
                return u
            K = self.body.tangent_stiffness(u)[free][:, free]
            step = spla.spsolve(K.tocsc(), residual)
            for _ in range(20):  # a Newton step that inverts an element (W undefined there) is halved
                trial = u.reshape(-1).copy()
                trial[free] += step
                trial = trial.reshape(self.n_nodes, self.dim)
                try:
                    residual = residual_at(trial)
                    break
                except FloatingPointError:
                    step = 0.5 * step
            else:
                break
            u = trial
        raise RuntimeError(f"elastic static equilibrium (load {np.abs(load).sum():.4g} N/m) did not converge in "
                           f"{max_iter} Newton steps; reduce scene.deflection_range")

    def modal_reference(self) -> tuple[np.ndarray, np.ndarray, sp.csr_matrix]:
        """(equilibrium under gravity u_g, first mode about it scaled to a unit vertical tip deflection), (nn, d)
        each, and the tangent stiffness K_t there (d nn × d nn), computed once."""
        if self._modal is None:
            u_g = self.static_equilibrium()
            free = self.free_dofs
            K_g = self.body.tangent_stiffness(u_g)
            mass = np.repeat(self.nodal_mass, self.dim)[free]
            _, vectors = spla.eigsh(K_g[free][:, free].tocsc(), k=1, M=sp.diags(mass).tocsc(), sigma=0, which="LM")
            mode = np.zeros(self.dim * self.n_nodes)
            mode[free] = vectors[:, 0]
            mode = mode.reshape(self.n_nodes, self.dim)
            self._modal = (u_g, mode / float(mode[self._tip, -1].mean()), K_g)
        return self._modal

    def modal_release(self, tip: np.ndarray) -> np.ndarray:
        """Equilibria (n, nn, d) under gravity and the modal load K_t δ φ₁ (the inertial load of the first mode
        at a turning point, whose linear response is δ φ₁), for tip deflections δ = `tip` (n,)."""
        u_g, mode, K = self.modal_reference()
        unit_load = -(K @ mode.reshape(-1)).reshape(self.n_nodes, self.dim)  # K_t φ₁ = ω₁² M φ₁ (a force on the body)
        return np.stack([self.static_equilibrium(-float(t) * unit_load, start=u_g) for t in np.asarray(tip).reshape(-1)])

    def release_velocity(self, speed: np.ndarray) -> np.ndarray:
        """Initial nodal velocities (n, nn, d) with tip speeds `speed` (n,), in the release's shape."""
        if self.release == "modal":
            _, mode, _ = self.modal_reference()
            return np.asarray(speed, dtype=np.float64)[:, None, None] * mode[None]
        return self.beam_shape(speed)

    def beam_shape(self, tip: np.ndarray) -> np.ndarray:
        """Nodal displacements (n, nn, d) of the Euler–Bernoulli tip-load shape with tip deflections `tip` (n,):
        u_d = w(X₁), u₁ = −(X_d − X_d,mid) w', the other components 0."""
        s = (self.body.nodes[:, 0] - self.x_min) / self.length
        w = 0.5 * s**2 * (3 - s)
        dw = 1.5 * s * (2 - s) / self.length
        shape = np.zeros((self.n_nodes, self.dim))
        shape[:, 0], shape[:, -1] = -(self.body.nodes[:, -1] - self.center) * dw, w
        return np.asarray(tip, dtype=np.float64)[:, None, None] * shape[None]

    def pack(self, u: np.ndarray, v: np.ndarray, load: np.ndarray) -> np.ndarray:
        """Full-order state (…, 2 d nn + 2) from u, v (…, nn, d) and load (…, 2) = (A, f)."""
        return np.concatenate([u.reshape(*u.shape[:-2], -1), v.reshape(*v.shape[:-2], -1), load], -1)

    def unpack(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nn, d = self.n_nodes, self.dim
        if states.shape[-1] != 2 * d * nn + 2:
            raise ValueError(f"{self.name} states must have 2·{d}·{nn} + 2 = {2 * d * nn + 2} entries ({nn} nodes), "
                             f"got {states.shape[-1]}")
        u = states[..., :d * nn].reshape(*states.shape[:-1], nn, d)
        v = states[..., d * nn:2 * d * nn].reshape(*states.shape[:-1], nn, d)
        return u, v, states[..., -2:]

    def sample_initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        tip = rng.uniform(*self.deflection_range, size=n)
        speed = rng.uniform(*self.tip_speed_range, size=n)
        load = np.stack([rng.uniform(*self.load_amplitude_range, size=n),
                         rng.uniform(*self.load_frequency_range, size=n)], -1)
        return self.pack(self.release_shape(tip), self.release_velocity(speed), load)

    def with_damping(self, rate: float) -> "ElasticCantilever":
        """The same body (and loads) with mass-proportional damping α = `rate` [1/s] in place of its own."""
        if not (np.isfinite(rate) and rate >= 0):
            raise ValueError(f"damping rate must be a finite number ≥ 0 [1/s], got {rate!r}")
        return type(self)(**{**self.params(), "damping": float(rate)})

    def released_at_rest(self, amplitude: float) -> np.ndarray:
        """The release shape with tip deflection `amplitude` [m], at rest and unloaded (amplitude 0 at the
        middle of the load-frequency range)."""
        load = np.array([[0.0, float(np.mean(self.load_frequency_range))]])
        return self.pack(self.release_shape(np.array([float(amplitude)])), self.release_velocity(np.array([0.0])),
                         load)[0]

    def stability_cases(self) -> StabilityCases:
        """Releases at rest, unloaded, from tip deflection 0.15 m (the edge of the default training range) to
        0.4 m."""
        return ELASTIC_CASES

    def external_force(self, t: float, load: np.ndarray) -> np.ndarray:
        """Nodal actuation forces (n, nn, d) at time t for load parameters (n, 2) (lumped)."""
        amplitude = load[:, 0] * np.sin(2 * np.pi * load[:, 1] * t)
        profile = np.clip((self.body.nodes[:, 0] - self.x_min) / self.length, 0, None) ** self.load_power
        shape = (self.body.volume_per_node * profile)[:, None] * np.asarray(self.load_direction)[None, :]
        return amplitude[:, None, None] * shape[None]

    def applied_force(self, u: np.ndarray, t: float, load: np.ndarray) -> np.ndarray:
        """Nodal forces (n, nn, d) [N] of the internal stress, gravity and actuation at time t (no damping)."""
        force = self.body.internal_force(u)
        force[..., -1] -= self.nodal_mass * self.gravity
        if self.loaded:
            force = force + self.external_force(t, load)
        return force

    def acceleration(self, u: np.ndarray, t: float, load: np.ndarray) -> np.ndarray:
        """Nodal accelerations (n, nn, d) of internal, gravity and actuation forces (no damping); 0 at the clamp."""
        acc = self.applied_force(u, t, load) / self.nodal_mass[None, :, None]
        acc[:, self.body.clamped] = 0.0
        return acc

    def simulate(self, initial_states: np.ndarray, times: np.ndarray, time_step: Optional[float] = None
                 ) -> np.ndarray:
        """The FEM body from `initial_states` sampled at `times` (uniform, from times[0]), by the scene's
        `integrator` at ≤ `time_step` (default the scene's)."""
        times = np.asarray(times, dtype=np.float64)
        u, v, load = (np.array(x, dtype=np.float64) for x in self.unpack(np.asarray(initial_states)))

        def force(u: np.ndarray, t: float, index: np.ndarray) -> np.ndarray:
            return self.applied_force(u, t, load[index])

        step = time_step or self.time_step
        try:
            if self.integrator == "verlet":
                us, vs = verlet(self.body, force, u, v, times, step, self.damping)
            else:
                us, vs, _ = implicit_midpoint(self.body, force, u, v, times, step, self.damping)
        except FloatingPointError as err:
            raise RuntimeError(f"elastic full-order model: {err} (scene.time_step, scene.cfl_fraction or "
                               "scene.integrator)") from err
        return self.pack(us, vs, np.repeat(load[:, None], len(times), 1))

    def _inside(self, points: np.ndarray) -> np.ndarray:
        """Points (N, d) clipped to the box (for a box-shaped mesh, its cells then hold every one of them)."""
        x = np.asarray(points, dtype=np.float64)
        lo, hi = np.asarray(self.bounds).T
        return np.clip(x, lo, hi)

    def fields(self, states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v, _ = self.unpack(np.asarray(states))
        interp = self.body.interpolation(self._inside(points))  # (N, nn)
        lead, N = u.shape[:-2], len(points)
        d = self.dim
        uv = np.concatenate([u, v], -1).reshape(-1, self.n_nodes, 2 * d)  # one product for both fields
        out = (interp @ uv.transpose(1, 0, 2).reshape(self.n_nodes, -1)).reshape(N, -1, 2 * d).transpose(1, 0, 2)
        out = out.reshape(*lead, N, 2 * d)
        return out[..., :d], out[..., d:]

    def field_gradients(self, states: np.ndarray, points: np.ndarray) -> np.ndarray:
        """∇_X u (…, N, d, d) [component a, direction j] of the FEM's displacement at points (N, d)."""
        return self._interpolated_gradients(self.unpack(np.asarray(states))[0], points)

    def velocity_gradients(self, states: np.ndarray, points: np.ndarray) -> np.ndarray:
        """∇_X u̇ (…, N, d, d) [component a, direction j] [1/s] of the FEM's velocity at points (N, d)."""
        return self._interpolated_gradients(self.unpack(np.asarray(states))[1], points)

    def _interpolated_gradients(self, nodal: np.ndarray, points: np.ndarray) -> np.ndarray:
        """∇_X of the interpolant of nodal vectors (…, nn, d) at points (N, d) → (…, N, d, d)."""
        lead, N, d = nodal.shape[:-2], len(points), self.dim
        flat = nodal.reshape(-1, self.n_nodes, d).transpose(1, 0, 2).reshape(self.n_nodes, -1)  # (nn, B·d)
        parts = [(D @ flat).reshape(N, -1, d) for D in self.body.interpolation_gradient(self._inside(points))]
        G = np.stack(parts, -1).transpose(1, 0, 2, 3)  # (B, N, d a, d j)
        return G.reshape(*lead, N, d, d)

    def nodal_potential(self, u: np.ndarray) -> np.ndarray:
        """The FEM body's potential V [J] (B,): strain energy plus gravity, for nodal displacements u (B, nn, d)."""
        return self.body.strain_energy(u) + self.gravity * (self.nodal_mass * u[..., -1]).sum(-1)

    def true_energy_parts(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v, _ = self.unpack(np.asarray(states))
        lead = u.shape[:-2]
        u2, v2 = u.reshape(-1, self.n_nodes, self.dim), v.reshape(-1, self.n_nodes, self.dim)
        kinetic = 0.5 * np.einsum("n,bnk,bnk->b", self.nodal_mass, v2, v2)
        return kinetic.reshape(lead), self.nodal_potential(u2).reshape(lead)
