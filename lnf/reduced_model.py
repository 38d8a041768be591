"""ReducedModel: what every reduced model in lnf shares — an embedding φ, a reduction ρ, and dynamics.

Our model (:class:`lnf.model.LagrangianNeuralField`) and the POD-Galerkin baseline
(:class:`lnf.baselines.pod.PODGalerkin`) differ only in φ (modulated SIREN or a linear map) and ρ
(K learned gradient steps or least squares); both pull the scene's Lagrangian back through the same
:class:`ReducedDynamics` and roll out with the same integrators. Shapes: codes q̃ (B, d); points
(N, dim_B) or (B, N, dim_B); fields (B, N, A).

Dtypes: tensors given to ``reduce``, ``project_velocity``, ``decode``, ``rollout`` and ``energy`` may have any
floating dtype (NumPy's float64 included) and device; they are converted to the model's own (float32 for a model
trained by ``lnf.train``; see :meth:`ReducedModel.as_model`), and what comes back is in the model's dtype.
"""
from __future__ import annotations

import contextlib
import copy
import inspect
import warnings
from typing import Any, Callable, Optional

import torch
from torch import Tensor, nn

from lnf.closure import CODE_SPAN_FLOOR, ClosedDynamics
from lnf.dynamics import ReducedDynamics
from lnf.integrators import Integrator, Trajectory, get_integrator
from lnf.quadrature import GaussLegendre, Quadrature, QuadratureRule
from lnf.reduction import project_velocity
from lnf.scenes.base import Scene
from lnf.threads import one_torch_thread


class OutsideBodyWarning(UserWarning):
    """:meth:`ReducedModel.decode` was given points outside the scene's bounds, where φ extrapolates."""


def as_field(values: Tensor) -> Tensor:
    """Accept (B, N) for scalar fields as well as (B, N, A)."""
    return values.unsqueeze(-1) if values.ndim == 2 else values


class ReducedModel(nn.Module):
    """Base class: `self.field` is φ with ``__call__(codes, points)`` and ``jet(codes, points, order, spatial)``.

    Subclasses implement :meth:`reduce`. `trainable` says whether ``lnf.train`` fits it by gradient descent
    (else it is fitted in closed form by :meth:`fit_to_observations`, or not at all).
    """

    trainable: bool = True
    state_is_field: bool = False  # True for the full-order model: its "codes" are the nodal field itself
    reduces_through_field: bool = False  # True where reduce() takes field= (ρ̃ iterates on φ: a table of φ may stand in)
    #: True where the codes are a learned field's (lnf's): dynamics that need codes (a table, a black box) apply
    learned_codes: bool = False
    #: what to try when the embedding collapses (projection floor near 1), in the model's own settings
    collapse_advice: str = "Train longer, or check that the data's fields vary between trajectories"
    field: nn.Module

    def __init__(self, scene: Scene, quadrature: Optional[QuadratureRule] = None) -> None:
        super().__init__()
        self.scene = scene
        self.quadrature_rule = quadrature if quadrature is not None else GaussLegendre(8)
        self.checkpoint: dict[str, Any] = {}
        self.closure: Optional[nn.Module] = None  # a potential closure ΔṼ fitted after training (lnf/closure.py)

    @property
    def latent_dim(self) -> int:
        return self.field.latent_dim

    def reference_tensor(self) -> Tensor:
        """A parameter or buffer, for the model's dtype and device."""
        for t in (*self.parameters(), *self.buffers()):
            return t
        return torch.zeros(())

    def as_model(self, x: Tensor) -> Tensor:
        """`x` in the model's floating dtype and on its device (:meth:`reference_tensor`): codes, fields and points
        of another dtype (float64 from NumPy) are converted rather than refused. A model without parameters or
        buffers leaves `x` as it is."""
        x = torch.as_tensor(x)
        for t in (*self.parameters(), *self.buffers()):
            if t.is_floating_point():
                return x.to(device=t.device, dtype=t.dtype)
            break
        return x

    def _density(self, points: Tensor) -> Tensor:
        return self.scene.density(points)

    # ------------------------------------------------------------------ embedding and reduction
    def decode(self, codes: Tensor, points: Tensor, chunk: int = 65536, outside: str = "warn") -> Tensor:
        """φ(q̃, X): codes (B, d), points (N, dim_B) or (B, N, dim_B) → (B, N, A) in the model's dtype (inputs of
        another dtype are converted to it). Chunked over points.

        φ is fitted on the body only; outside the scene's ``bounds`` it extrapolates. `outside`: what points outside
        the bounds (beyond a relative 1e-5 of the box) do: ``"warn"`` (one :class:`OutsideBodyWarning` per call,
        naming how many and the bounds), ``"error"`` (a ValueError saying the same) or ``"ignore"``. Only the box
        is known: inside it, points in a cut-out of a body that does not fill its box are not detected."""
        codes = self.as_model(codes)
        points = self.as_model(points)
        self._check_inside(points, outside)
        if points.shape[-2] <= chunk:
            return self.field(codes, points)
        parts = [self.field(codes, points[..., i:i + chunk, :]) for i in range(0, points.shape[-2], chunk)]
        return torch.cat(parts, dim=-2)

    def _check_inside(self, points: Tensor, outside: str) -> None:
        """Warn about (or refuse) points outside the scene's bounds: what :meth:`decode` does with `outside`."""
        if outside not in ("warn", "error", "ignore"):
            raise ValueError(f"decode(outside=...) must be 'warn', 'error' or 'ignore', got {outside!r}")
        if outside == "ignore" or points.shape[-1] != self.scene.body_dim:
            return
        box = torch.as_tensor(self.scene.bounds, dtype=points.dtype, device=points.device)  # (dim_B, 2)
        tol = 1e-5 * (box[:, 1] - box[:, 0])
        out = ((points < box[:, 0] - tol) | (points > box[:, 1] + tol)).any(-1)
        n_out = int(out.sum())
        if not n_out:
            return
        message = (f"decode: {n_out} of {out.numel()} points lie outside the body's bounds {self.scene.bounds} "
                   f"(scene {self.scene.name!r}), where φ, fitted on the body only, extrapolates; pass points inside "
                   f"the bounds, or outside='ignore' to accept extrapolation ('error' to refuse it)")
        if outside == "error":
            raise ValueError(message)
        warnings.warn(message, OutsideBodyWarning, stacklevel=3)

    def reduce(self, points: Tensor, values: Tensor, steps: Optional[int] = None) -> Tensor:
        """ρ(q): observed field values (B, N, A) at points → codes (B, d)."""
        raise NotImplementedError

    def fit_to_observations(self, points: Tensor, values: Tensor) -> dict[str, float]:
        """Closed-form fit to training observations (n, Nobs, dim_B), (n, T, Nobs, A); for non-trainable models."""
        raise NotImplementedError(f"{type(self).__name__} is trained by gradient descent, not in closed form")

    def project_velocity(self, codes: Tensor, points: Tensor, velocities: Tensor,
                         weights: Optional[Tensor] = None) -> Tensor:
        """q̃̇ = (dφ)† q̇ (†: the ω0-weighted pseudo-inverse): velocity field (B, N, A) at points → (B, d).

        `weights` are quadrature weights of the points (N,); uniform (|B|/N) if omitted. Returned in the model's
        dtype (inputs of another dtype are converted to it).
        """
        velocities = as_field(self.as_model(velocities))
        codes = self.as_model(codes)
        points = self.as_model(points)
        self._check_observation(points, velocities, "velocities")
        if weights is None:
            weights = points.new_full(points.shape[:-1], 1.0 / points.shape[-2])
        ww = weights.to(velocities) * self._density(points)
        return project_velocity(self.field.jet(codes, points, order=1).J, ww, velocities)

    def _check_observation(self, points: Tensor, values: Tensor, what: str) -> None:
        if points.shape[-1] != self.scene.body_dim or points.shape[-2] == 0:
            raise ValueError(f"points must have shape (N, {self.scene.body_dim}) with N ≥ 1, got {tuple(points.shape)}")
        if values.ndim != 3 or values.shape[-2] != points.shape[-2] or values.shape[-1] != self.scene.field_dim:
            raise ValueError(f"{what} must have shape (B, {points.shape[-2]}, {self.scene.field_dim}) to match "
                             f"points {tuple(points.shape)}, got {tuple(values.shape)}")
        if not torch.isfinite(values).all():
            raise ValueError(f"{what} contain NaN or inf")

    # ------------------------------------------------------------------ reduced dynamics
    def lagrangian_dynamics(self, quadrature: "Quadrature | QuadratureRule | None" = None,
                            dtype: Optional[torch.dtype] = None) -> ReducedDynamics:
        """The scene's Lagrangian pulled back through φ on `quadrature` (default: the model's rule).

        `dtype` other than the model's evaluates a copy of φ in that precision (e.g. float64 for tables)."""
        rule = quadrature if quadrature is not None else self.quadrature_rule
        quad = rule if isinstance(rule, Quadrature) else rule.build_for(self.scene)
        p = self.reference_tensor()
        field = self.field
        if dtype is not None and dtype != p.dtype:
            field = copy.deepcopy(self.field).to(dtype)
        return ReducedDynamics(field.jet, self.scene, quad.to(device=p.device, dtype=dtype or p.dtype))

    def dynamics(self, quadrature: "Quadrature | QuadratureRule | None" = None) -> Any:
        """The dynamics that rollouts integrate (the pulled-back Lagrangian unless a subclass says otherwise), with
        the model's closure once fitted."""
        return self.closed(self.lagrangian_dynamics(quadrature))

    @property
    def code_span_floor(self) -> float:
        """The least span a code is measured by, as a fraction of the largest code's (a potential closure's scale, its
        shooting guard, a table's box): :data:`lnf.closure.CODE_SPAN_FLOOR` where φ's codes share one unit (its
        ``commensurate_codes``: POD modes of equal L² norm, so a code's size is the field's), 0 where each code has its
        own (a SIREN's)."""
        return CODE_SPAN_FLOOR if getattr(self.field, "commensurate_codes", False) else 0.0

    @property
    def has_closure(self) -> bool:
        """Whether the model carries a fitted (non-zero) potential closure ΔṼ (lnf/closure.py)."""
        return self.closure is not None and self.closure.active

    def closed(self, dynamics: Any) -> Any:
        """`dynamics` with the model's fitted closure added (lnf/closure.py), or as it is."""
        return ClosedDynamics(dynamics, self.closure) if self.has_closure else dynamics

    def rollout(self, q0: Tensor, v0: Tensor, dt: float, steps: int,
                integrator: "str | Integrator | dict" = "implicit_midpoint", record_every: int = 1,
                quadrature: "Quadrature | QuadratureRule | None" = None,
                on_divergence: str = "raise", controls: Optional[Tensor] = None, dynamics: Any = None,
                progress: Optional[Callable[[int], None]] = None, t0: float = 0.0) -> Trajectory:
        """Integrate the reduced dynamics from (q̃0, q̃̇0) (B, d) at time `t0` [s] for `steps` steps of `dt` [s].

        `controls` (B, c): per-trajectory load parameters of a forced scene (:meth:`Scene.controls`).
        `dynamics`: what :meth:`dynamics` (`quadrature`) returned, if the caller already built it.
        `progress(k)`: told of every k steps done (e.g. a progress bar's advance).
        q̃0, q̃̇0 and `controls` of another dtype (float64) are converted to the model's; the trajectory is in it.
        """
        q0, v0 = self.as_model(q0), self.as_model(v0)
        dynamics = self.dynamics(quadrature) if dynamics is None else dynamics
        if controls is not None:
            if not hasattr(dynamics, "controls"):
                raise ValueError(f"{type(dynamics).__name__} takes no external loads, but controls were given")
            if controls.ndim != 2 or controls.shape[0] != q0.shape[0]:
                raise ValueError(f"controls must have shape (B={q0.shape[0]}, c), got {tuple(controls.shape)}")
            dynamics.controls = controls.to(q0)
        integ = get_integrator(integrator)
        # an integrator of a user's own whose integrate() takes no progress callback runs without a progress bar
        extra = {"progress": progress} if progress is not None and \
            "progress" in inspect.signature(integ.integrate).parameters else {}
        # a dynamics of small tensors (a table) runs on one thread: its ops are too small for a thread pool
        threads = one_torch_thread() if getattr(dynamics, "small_tensors", False) else contextlib.nullcontext()
        with torch.no_grad(), threads:
            return integ.integrate(dynamics, q0, v0, dt, steps, record_every=record_every, t0=t0,
                                   on_divergence=on_divergence, **extra)

    def energy(self, q: Tensor, v: Tensor, quadrature: "Quadrature | QuadratureRule | None" = None
               ) -> tuple[Tensor, Tensor]:
        """(T̃, Ṽ) of reduced states q̃, q̃̇ (..., d) → each (...): the scene's energy pulled back through φ, plus a
        fitted potential closure ΔṼ where the model has one (inputs of another dtype are converted to the model's)."""
        q, v = self.as_model(q), self.as_model(v)
        with torch.no_grad():
            kinetic, potential = self.lagrangian_dynamics(quadrature).energies(q, v)
            if self.has_closure:  # the closed system's energy (lnf/closure.py)
                potential = potential + self.closure.potential(q.reshape(-1, q.shape[-1])).reshape(potential.shape)
            return kinetic, potential

    def extra_repr(self) -> str:
        return f"scene={self.scene!r}, quadrature={self.quadrature_rule.describe()}"
