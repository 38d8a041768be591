"""A hyperelastic cantilever under gravity (the paper's target): St Venant–Kirchhoff, plane strain, 2-D.

Body B = [0, L] × [0, H], clamped at X₁ = 0, mass density ρ. The configuration field is the displacement
u: B → ℝ² (positions X + u), so `field_rel_l2` is normalised by the displacement from the reference
configuration. The Lagrangian (docs/method.md §5.1):

    T = ½ ∫ ρ ‖u̇‖² dX,   V = ∫ W(I + ∇_X u) dX + ∫ ρ g u₂ dX,   W(F) = μ E:E + ½ λ (tr E)².

Optional non-conservative forces (the paper's future work), per unit reference area:
mass-proportional Rayleigh damping −α ρ u̇ and a vertical actuation load b(X, t) = A sin(2π f t) (X₁/L) e₂
with per-trajectory amplitude A and frequency f (the scene's `controls`).

Ground truth: the Q1 finite-element model of :mod:`lnf.scenes.fem` with lumped mass and velocity Verlet
(symplectic; with damping, a conformal splitting), at a time step below the CFL limit. Initial states
(`release`), with δ ~ U(deflection_range) and a tip speed ~ U(tip_speed_range):

- ``"shape"``: the Euler–Bernoulli tip-load shape w(X₁) = δ (X₁/L)² (3 − X₁/L)/2, u₁ = −(X₂ − H/2) w', with an
  initial velocity of the same shape. It is not an equilibrium of the FEM body, so the release also excites
  its fast modes (axial, shear, higher bending), which carry a large share of the velocity.
- ``"modal"``: from the FEM's own nonlinear static equilibrium under gravity plus the load K_t δ φ₁,
  φ₁ the first bending mode about the gravity equilibrium (scaled to a unit tip deflection) and K_t the
  tangent stiffness there: the inertial load of that mode at a turning point, whose linear response is δ φ₁.
  The load is removed at t = 0; the initial velocity is the tip speed times φ₁. The fast modes stay nearly at
  rest: on 16 runs (δ ≤ 0.15 m, tip speed ≤ 0.5 m/s) 2 POD modes leave 1.6 % of the displacement and 3.2 % of
  the velocity, against 6.4 % and 64 % for ``"shape"`` (`python experiments/elastic_diagnostics.py --content`).
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

from lnf.quadrature import Quadrature
from lnf.scenes.base import DiscretePotential, GeneralizedForce, Scene, StabilityCases, check_positive, check_range
from lnf.scenes.fem import StructuredQ1Mesh, lame

log = logging.getLogger("lnf.scenes.elastic")

# the stability study's high-energy releases: tip deflections δ [m] from the default deflection_range's edge
ELASTIC_CASES = StabilityCases((0.15, 0.2, 0.25, 0.3, 0.4), "tip deflection of the release at rest δ [m]", 0.15,
                               "training range |δ| ≤ 0.15 m")


def svk_torch(G: Tensor, lam: float, mu: float) -> tuple[Tensor, Tensor]:
    """(W, P) of St Venant–Kirchhoff at F = I + G for displacement gradients G (…, 2, 2)."""
    F = G + torch.eye(2, dtype=G.dtype, device=G.device)
    E = 0.5 * (F.transpose(-1, -2) @ F - torch.eye(2, dtype=G.dtype, device=G.device))
    trace = E[..., 0, 0] + E[..., 1, 1]
    W = mu * (E * E).sum((-1, -2)) + 0.5 * lam * trace**2
    S = 2 * mu * E + lam * trace[..., None, None] * torch.eye(2, dtype=G.dtype, device=G.device)
    return W, F @ S


class ElasticPotential(DiscretePotential):
    """V = Σ_j w_j [W(I + G_j) + ρ g q_{j,2}] on quadrature points; q (B, N, 2), G = ∇_X q (B, N, 2, 2)."""

    needs_gradient = True

    def __init__(self, weights: Tensor, lam: float, mu: float, rho_g: float) -> None:
        self.weights, self.lam, self.mu, self.rho_g = weights, lam, mu, rho_g

    def __call__(self, q: Tensor, G: Optional[Tensor] = None) -> Tensor:
        W, _ = svk_torch(G, self.lam, self.mu)
        w = self.weights.to(q)
        return torch.einsum("n,bn->b", w, W + self.rho_g * q[..., 1])

    def gradient(self, q: Tensor, G: Optional[Tensor] = None) -> tuple[Tensor, Tensor]:
        _, P = svk_torch(G, self.lam, self.mu)
        w = self.weights.to(q)
        dq = torch.zeros_like(q)
        dq[..., 1] = self.rho_g * w
        return dq, w[:, None, None] * P


class CantileverLoad(GeneralizedForce):
    """f = −α ρ u̇ + A sin(2π f t) (X₁/L) e₂ at quadrature points; controls (B, 2) = (A, f)."""

    def __init__(self, weights: Tensor, points: Tensor, length: float, rho: float, damping: float) -> None:
        super().__init__(weights)
        self.profile = points[:, 0] / length  # (N,)
        self.rho, self.damping = rho, damping

    def field_force(self, t: float, q: Tensor, v: Tensor, controls: Optional[Tensor]) -> Tensor:
        force = -self.damping * self.rho * v
        if controls is not None:
            amplitude = controls[:, 0] * torch.sin(2 * math.pi * controls[:, 1] * t)  # (B,)
            force = force.clone()
            force[..., 1] = force[..., 1] + amplitude[:, None] * self.profile.to(v)[None, :]
        return force


class ElasticCantilever(Scene):
    """A 2-D St Venant–Kirchhoff cantilever under gravity, clamped at X₁ = 0 (units: m, kg, s, Pa per m depth).

    Args:
        length, height: L, H of the body B = [0, L] × [0, H].
        density: ρ; young, poisson: E, ν (plane strain); gravity: g (acts along −X₂).
        mesh: (nx, ny) Q1 elements of the full-order model.
        time_step: full-order Verlet step [s]; null = `cfl_fraction` × the CFL estimate.
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
                 time_step: Optional[float] = None, cfl_fraction: float = 0.5,
                 deflection_range: Sequence[float] = (-0.15, 0.15), tip_speed_range: Sequence[float] = (-0.5, 0.5),
                 damping: float = 0.0, load_amplitude_range: Sequence[float] = (0.0, 0.0),
                 load_frequency_range: Sequence[float] = (0.5, 1.0), release: str = "shape") -> None:
        check_positive(length=length, height=height, density=density, young=young, cfl_fraction=cfl_fraction)
        if not 0 <= poisson < 0.5:
            raise ValueError(f"scene.poisson must be in [0, 0.5), got {poisson!r}")
        for key, value in [("gravity", gravity), ("damping", damping)]:
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"scene.{key} must be a finite number ≥ 0, got {value!r}")
        if len(mesh) != 2 or any(int(n) != n or n < 1 for n in mesh):
            raise ValueError(f"scene.mesh must be two integers (nx, ny) ≥ 1, got {list(mesh)!r}")
        if release not in ("shape", "modal"):
            raise ValueError(f"scene.release must be 'shape' or 'modal', got {release!r}")
        check_range(deflection_range=deflection_range, tip_speed_range=tip_speed_range,
                    load_amplitude_range=load_amplitude_range, load_frequency_range=load_frequency_range)
        self.length, self.height, self.rho = float(length), float(height), float(density)
        self.young, self.poisson, self.gravity = float(young), float(poisson), float(gravity)
        self.mesh_shape = [int(n) for n in mesh]
        self.cfl_fraction = float(cfl_fraction)
        self.deflection_range = [float(v) for v in deflection_range]
        self.tip_speed_range = [float(v) for v in tip_speed_range]
        self.damping = float(damping)
        self.load_amplitude_range = [float(v) for v in load_amplitude_range]
        self.load_frequency_range = [float(v) for v in load_frequency_range]
        self.loaded = any(v != 0 for v in self.load_amplitude_range)  # actuation present
        self.release = str(release)
        self.bounds = [[0.0, self.length], [0.0, self.height]]
        self.lam, self.mu = lame(self.young, self.poisson)
        self.mesh = StructuredQ1Mesh(self.length, self.height, *self.mesh_shape)
        cfl = self.mesh.stable_time_step(self.lam, self.mu, self.rho)
        self.time_step = float(time_step) if time_step is not None else self.cfl_fraction * cfl
        if not (np.isfinite(self.time_step) and self.time_step > 0):
            raise ValueError(f"scene.time_step must be a positive number [s], got {time_step!r}")
        self.nodal_mass = self.rho * self.mesh.nodal_area  # (nn,)
        self.free_dofs = np.flatnonzero(np.repeat(~self.mesh.clamped, 2))  # unclamped nodal dofs of u.reshape(-1)
        self._tip = np.flatnonzero(self.mesh.nodes[:, 0] == self.length)
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
                mass = float(np.repeat(self.nodal_mass, 2) @ flat**2)
                scale = 0.5 * delta**2 * stiffness + 0.5 * speed**2 * mass
            else:
                scale = float(self.mesh.strain_energy(self.beam_shape(np.array([delta])), self.lam, self.mu)[0])
            self._energy_scale = scale if scale > 0 else self.rho * max(self.gravity, 1.0) * self.length**2 * self.height
        return self._energy_scale

    def params(self) -> dict[str, Any]:
        return dict(length=self.length, height=self.height, density=self.rho, young=self.young,
                    poisson=self.poisson, gravity=self.gravity, mesh=self.mesh_shape,
                    time_step=self.time_step, cfl_fraction=self.cfl_fraction,
                    deflection_range=self.deflection_range, tip_speed_range=self.tip_speed_range,
                    damping=self.damping, load_amplitude_range=self.load_amplitude_range,
                    load_frequency_range=self.load_frequency_range, release=self.release)

    # -- the Lagrangian ---------------------------------------------------------------------------------
    def density(self, points: Tensor) -> Tensor:
        return torch.full(points.shape[:-1], self.rho, dtype=points.dtype, device=points.device)

    def potential(self, quadrature: Quadrature) -> ElasticPotential:
        return ElasticPotential(quadrature.weights, self.lam, self.mu, self.rho * self.gravity)

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
        return CantileverLoad(quadrature.weights, quadrature.points, self.length, self.rho, self.damping)

    def clamp_factor(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """s = X₁/L (zero on the clamp X₁ = 0) and ∇s = (1/L, 0), for points (…, N, 2)."""
        s = points[..., 0] / self.length
        ds = torch.zeros_like(points)
        ds[..., 0] = 1.0 / self.length
        return s, ds

    def controls(self, states: np.ndarray) -> Optional[np.ndarray]:
        return np.asarray(states)[..., -2:] if self.forced else None

    # -- the full-order model ---------------------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return self.mesh.n_nodes

    def release_shape(self, tip: np.ndarray) -> np.ndarray:
        """Nodal displacements (n, nn, 2) of the release with tip deflections `tip` (n,) (see `release`)."""
        if self.release == "modal":
            return self.modal_release(np.asarray(tip, dtype=np.float64))
        return self.beam_shape(tip)

    def static_equilibrium(self, nodal_load: Optional[np.ndarray] = None, start: Optional[np.ndarray] = None,
                           tol: float = 1e-10, max_iter: int = 30) -> np.ndarray:
        """Nodal displacements (nn, 2) at rest under gravity and extra nodal forces (nn, 2) [N/m] (Newton)."""
        u = np.zeros((self.n_nodes, 2)) if start is None else np.array(start, dtype=np.float64)
        load = np.zeros((self.n_nodes, 2)) if nodal_load is None else np.array(nodal_load, dtype=np.float64)
        load[:, 1] -= self.nodal_mass * self.gravity
        free = self.free_dofs
        scale = max(np.abs(load).sum(), 1e-300)
        for _ in range(max_iter):
            residual = (self.mesh.internal_force(u[None], self.lam, self.mu)[0] + load).reshape(-1)[free]
            if np.abs(residual).sum() <= tol * scale:
                return u
            K = self.mesh.tangent_stiffness(u, self.lam, self.mu)[free][:, free]
            step = spla.spsolve(K.tocsc(), residual)
            u = u.reshape(-1).copy()
            u[free] += step
            u = u.reshape(self.n_nodes, 2)
        raise RuntimeError(f"elastic static equilibrium (load {np.abs(load).sum():.4g} N/m) did not converge in "
                           f"{max_iter} Newton steps; reduce scene.deflection_range")

    def modal_reference(self) -> tuple[np.ndarray, np.ndarray, sp.csr_matrix]:
        """(equilibrium under gravity u_g, first bending mode about it scaled to a unit tip deflection), (nn, 2)
        each, and the tangent stiffness K_t there (2 nn × 2 nn), computed once."""
        if self._modal is None:
            u_g = self.static_equilibrium()
            free = self.free_dofs
            K_g = self.mesh.tangent_stiffness(u_g, self.lam, self.mu)
            mass = np.repeat(self.nodal_mass, 2)[free]
            _, vectors = spla.eigsh(K_g[free][:, free].tocsc(), k=1, M=sp.diags(mass).tocsc(), sigma=0, which="LM")
            mode = np.zeros(2 * self.n_nodes)
            mode[free] = vectors[:, 0]
            mode = mode.reshape(self.n_nodes, 2)
            self._modal = (u_g, mode / float(mode[self._tip, 1].mean()), K_g)
        return self._modal

    def modal_release(self, tip: np.ndarray) -> np.ndarray:
        """Equilibria (n, nn, 2) under gravity and the modal load K_t δ φ₁ (the inertial load of the first mode
        at a turning point, whose linear response is δ φ₁), for tip deflections δ = `tip` (n,)."""
        u_g, mode, K = self.modal_reference()
        unit_load = -(K @ mode.reshape(-1)).reshape(self.n_nodes, 2)  # K_t φ₁ = ω₁² M φ₁ (a force on the body)
        return np.stack([self.static_equilibrium(-float(t) * unit_load, start=u_g) for t in np.asarray(tip).reshape(-1)])

    def release_velocity(self, speed: np.ndarray) -> np.ndarray:
        """Initial nodal velocities (n, nn, 2) with tip speeds `speed` (n,), in the release's shape."""
        if self.release == "modal":
            _, mode, _ = self.modal_reference()
            return np.asarray(speed, dtype=np.float64)[:, None, None] * mode[None]
        return self.beam_shape(speed)

    def beam_shape(self, tip: np.ndarray) -> np.ndarray:
        """Nodal displacements (n, nn, 2) of the Euler–Bernoulli tip-load shape with tip deflections `tip` (n,)."""
        s = self.mesh.nodes[:, 0] / self.length
        w = 0.5 * s**2 * (3 - s)
        dw = 1.5 * s * (2 - s) / self.length
        shape = np.stack([-(self.mesh.nodes[:, 1] - 0.5 * self.height) * dw, w], -1)  # (nn, 2)
        return np.asarray(tip, dtype=np.float64)[:, None, None] * shape[None]

    def pack(self, u: np.ndarray, v: np.ndarray, load: np.ndarray) -> np.ndarray:
        """Full-order state (…, 4 nn + 2) from u, v (…, nn, 2) and load (…, 2) = (A, f)."""
        return np.concatenate([u.reshape(*u.shape[:-2], -1), v.reshape(*v.shape[:-2], -1), load], -1)

    def unpack(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nn = self.n_nodes
        if states.shape[-1] != 4 * nn + 2:
            raise ValueError(f"elastic states must have 4·{nn} + 2 = {4 * nn + 2} entries (mesh {self.mesh_shape}), "
                             f"got {states.shape[-1]}")
        u = states[..., :2 * nn].reshape(*states.shape[:-1], nn, 2)
        v = states[..., 2 * nn:4 * nn].reshape(*states.shape[:-1], nn, 2)
        return u, v, states[..., -2:]

    def sample_initial_states(self, n: int, rng: np.random.Generator) -> np.ndarray:
        tip = rng.uniform(*self.deflection_range, size=n)
        speed = rng.uniform(*self.tip_speed_range, size=n)
        load = np.stack([rng.uniform(*self.load_amplitude_range, size=n),
                         rng.uniform(*self.load_frequency_range, size=n)], -1)
        return self.pack(self.release_shape(tip), self.release_velocity(speed), load)

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
        """Nodal actuation forces (n, nn, 2) at time t for load parameters (n, 2) (lumped)."""
        amplitude = load[:, 0] * np.sin(2 * np.pi * load[:, 1] * t)
        f = np.zeros((len(load), self.n_nodes, 2))
        f[..., 1] = amplitude[:, None] * (self.mesh.nodal_area * self.mesh.nodes[:, 0] / self.length)[None]
        return f

    def acceleration(self, u: np.ndarray, t: float, load: np.ndarray) -> np.ndarray:
        """Nodal accelerations (n, nn, 2) of internal, gravity and actuation forces (no damping); 0 at the clamp."""
        force = self.mesh.internal_force(u, self.lam, self.mu)
        force[..., 1] -= self.nodal_mass * self.gravity
        if self.loaded:
            force = force + self.external_force(t, load)
        acc = force / self.nodal_mass[None, :, None]
        acc[:, self.mesh.clamped] = 0.0
        return acc

    def simulate(self, initial_states: np.ndarray, times: np.ndarray, time_step: Optional[float] = None
                 ) -> np.ndarray:
        """Velocity Verlet at ≤ `time_step` (default the scene's), sampled at `times` (uniform, from times[0])."""
        times = np.asarray(times, dtype=np.float64)
        u, v, load = (np.array(x, dtype=np.float64) for x in self.unpack(np.asarray(initial_states)))
        out = np.empty((len(u), len(times), 4 * self.n_nodes + 2))
        out[:, 0] = self.pack(u, v, load)
        if len(times) == 1:
            return out
        sample = float(times[1] - times[0])
        substeps = max(1, math.ceil(sample / (time_step or self.time_step) - 1e-9))
        h = sample / substeps
        decay = math.exp(-0.5 * self.damping * h)
        t = float(times[0])
        acc = self.acceleration(u, t, load)
        for k in range(1, len(times)):
            for _ in range(substeps):
                v = decay * v + 0.5 * h * acc
                u = u + h * v
                t += h
                acc = self.acceleration(u, t, load)
                v = decay * (v + 0.5 * h * acc)
            if not np.isfinite(u).all():
                raise RuntimeError(f"elastic full-order model diverged at t = {t:.4g} s with time step {h:.3g} s; "
                                   "set scene.time_step smaller (or scene.cfl_fraction)")
            out[:, k] = self.pack(u, v, load)
        return out

    def fields(self, states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v, _ = self.unpack(np.asarray(states))
        interp = self.mesh.interpolation(np.asarray(points, dtype=np.float64))  # (N, nn)
        lead, N = u.shape[:-2], len(points)
        uv = np.concatenate([u, v], -1).reshape(-1, self.n_nodes, 4)  # one product for both fields
        out = (interp @ uv.transpose(1, 0, 2).reshape(self.n_nodes, -1)).reshape(N, -1, 4).transpose(1, 0, 2)
        out = out.reshape(*lead, N, 4)
        return out[..., :2], out[..., 2:]

    def field_gradients(self, states: np.ndarray, points: np.ndarray) -> np.ndarray:
        """∇_X u (…, N, 2, 2) [component a, direction j] of the FEM's bilinear displacement at points (N, 2)."""
        return self._interpolated_gradients(self.unpack(np.asarray(states))[0], points)

    def velocity_gradients(self, states: np.ndarray, points: np.ndarray) -> np.ndarray:
        """∇_X u̇ (…, N, 2, 2) [component a, direction j] [1/s] of the FEM's bilinear velocity at points (N, 2)."""
        return self._interpolated_gradients(self.unpack(np.asarray(states))[1], points)

    def _interpolated_gradients(self, nodal: np.ndarray, points: np.ndarray) -> np.ndarray:
        """∇_X of the bilinear interpolant of nodal vectors (…, nn, 2) at points (N, 2) → (…, N, 2, 2)."""
        lead, N = nodal.shape[:-2], len(points)
        flat = nodal.reshape(-1, self.n_nodes, 2).transpose(1, 0, 2).reshape(self.n_nodes, -1)  # (nn, B·2)
        parts = [(D @ flat).reshape(N, -1, 2) for D in self.mesh.interpolation_gradient(np.asarray(points, np.float64))]
        G = np.stack(parts, -1).transpose(1, 0, 2, 3)  # (B, N, 2a, 2j)
        return G.reshape(*lead, N, 2, 2)

    def nodal_potential(self, u: np.ndarray) -> np.ndarray:
        """The FEM body's potential V [J/m] (B,): strain energy plus gravity, for nodal displacements u (B, nn, 2)."""
        return self.mesh.strain_energy(u, self.lam, self.mu) + self.gravity * (self.nodal_mass * u[..., 1]).sum(-1)

    def true_energy_parts(self, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v, _ = self.unpack(np.asarray(states))
        lead = u.shape[:-2]
        u2, v2 = u.reshape(-1, self.n_nodes, 2), v.reshape(-1, self.n_nodes, 2)
        kinetic = 0.5 * np.einsum("n,bnk,bnk->b", self.nodal_mass, v2, v2)
        return kinetic.reshape(lead), self.nodal_potential(u2).reshape(lead)
