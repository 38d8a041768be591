"""A potential closure of the pulled-back dynamics, fitted to the observed motion after training.

The pulled-back equations M̃q̃̈ + c̃ + g̃ = τ̃ are exact only where φ's manifold is invariant under the continuum's
motion. A low-dimensional manifold of an elastic body is not: along the encoded training trajectories the residual
r = M̃q̃̈ + c̃ + g̃ − τ̃ (q̃̈ by finite differences of the encoded velocities) is several per cent of the forces, and
over many periods that becomes a phase error. The closure adds a potential ΔṼ(q̃), a polynomial of total degree
1 … p in the scaled codes x = (q̃ − c)/s, whose gradient is fitted to −r by ridge least squares:

    L̃ = T̃(q̃, q̃̇) − Ṽ(q̃) − ΔṼ(q̃),    M̃q̃̈ + c̃ + g̃ + ∇ΔṼ = τ̃.

The reduced system stays Lagrangian (its energy T̃ + Ṽ + ΔṼ is conserved, the symplectic integrators apply), but
it is no longer the pure pullback of the known Lagrangian: ΔṼ is fitted to data, in the spirit of Operator
Inference, on top of the physics. Off by default (``model.closure_degree: 0``); ``+experiment=elastic`` sets 4.
"""
from __future__ import annotations

import itertools
import math
from typing import Any, Optional

import torch
from torch import Tensor, nn


def monomial_exponents(latent_dim: int, degree: int) -> Tensor:
    """Exponents (P, d) of every monomial of total degree 1 … `degree` in d variables: the linear ones give a
    constant force (a shifted equilibrium), the quadratic ones a stiffness, the higher ones its amplitude dependence;
    the span does not depend on where the variables are centred."""
    rows = []
    for total in range(1, degree + 1):
        for combo in itertools.combinations_with_replacement(range(latent_dim), total):
            rows.append([combo.count(i) for i in range(latent_dim)])
    return torch.tensor(rows, dtype=torch.long)


#: the most terms of a closure by default (``model.closure_max_terms``, ``closure_max_terms`` of lnf.evaluate): d = 2 at
#: degree 4
CLOSURE_MAX_TERMS = 14


def closure_terms(latent_dim: int, degree: int) -> int:
    """The number of monomials of total degree 1 … `degree` in `latent_dim` variables: C(d + p, p) − 1."""
    return math.comb(int(latent_dim) + int(degree), int(degree)) - 1


def capped_degree(latent_dim: int, degree: int, max_terms: Optional[int]) -> int:
    """The largest degree p in [2, `degree`] whose closure has at most `max_terms` terms (2 where none has; `degree`
    itself for `max_terms` None): at degree 4, d = 1, 2 keep 4 (4 and 14 terms), d = 3, 4 get 2 (9 and 14 terms,
    where degree 4 has 34 and 69)."""
    p = int(degree)
    while max_terms is not None and p > 2 and closure_terms(latent_dim, p) > int(max_terms):
        p -= 1
    return p


#: the least span a code is given, as a fraction of the largest code's (:func:`floored_spans`), where the codes share
#: one unit (POD coordinates: :attr:`lnf.reduced_model.ReducedModel.code_span_floor`): a closure fitted so is a
#: candidate beside one on each code's own span (lnf/closure_choice.py); the shooting's guard and a table's box
#: (lnf/model.py) measure by these spans. The soft body's 3rd and 4th POD codes span 0.3 % of its 1st's (the
#: cantilever's 2nd and 3rd 7 and 1 %): on its own span a quadratic term in such a code is a stiffness θ/span²; at
#: d = 4 the soft body's rollouts swing its 4th code a few of its own widths, a small change of the field, past a
#: table's box of its own span, where the shooting's trials read the table's edge and ran 1 090 half-widths away
CODE_SPAN_FLOOR = 0.1


def floored_spans(span: Tensor, floor: float) -> Tensor:
    """Each code's `span` (d,), raised to at least `floor` × the largest (0: unchanged)."""
    return torch.maximum(span, float(floor) * span.max()) if floor > 0 else span


class PotentialClosure(nn.Module):
    """ΔṼ(q̃) = Σ_p θ_p Π_i x_i^{E_pi}, x = (q̃ − center)/scale, for a d-dimensional code; all zeros until fitted.

    The polynomial holds on the fitted box |x_i| ≤ 1 (the training codes lie in it); beyond it ΔṼ continues as its
    first-order Taylor expansion from the nearest point of the box, so the closure's force stays continuous and
    bounded there (a quartic would otherwise carry a rollout that reaches past the training codes away), and the
    closed dynamics stay conservative: :meth:`gradient` is the exact gradient of :meth:`potential` everywhere.

    Args:
        latent_dim: d.
        degree: the largest total degree p ≥ 2 (2: a constant force and a linear stiffness correction).
        max_terms: None, or the most terms: the degree is lowered (not below 2) until the closure has at most this
            many (:func:`capped_degree`; ``model.closure_max_terms``: :data:`CLOSURE_MAX_TERMS` in conf/model/lnf.yaml).
    """

    def __init__(self, latent_dim: int, degree: int, max_terms: Optional[int] = None) -> None:
        super().__init__()
        if int(degree) < 2:
            raise ValueError(f"model.closure_degree must be 0 (no closure) or ≥ 2, got {degree!r}")
        if max_terms is not None and int(max_terms) < 1:
            raise ValueError(f"model.closure_max_terms must be null (no cap) or ≥ 1, got {max_terms!r}")
        #: the degree in use: `degree`, lowered to :func:`capped_degree` under `max_terms`
        self.degree = capped_degree(int(latent_dim), int(degree), max_terms)
        self.register_buffer("exponents", monomial_exponents(int(latent_dim), self.degree))
        self.register_buffer("center", torch.zeros(int(latent_dim)))
        self.register_buffer("scale", torch.ones(int(latent_dim)))
        self.register_buffer("coef", torch.zeros(len(self.exponents)))
        #: None, or the box (low, high) (d,) each beyond which the closure's force is NaN (:meth:`set_guard`)
        self._guard: Optional[tuple[Tensor, Tensor]] = None
        self._fitted_range: Optional[tuple[Tensor, Tensor]] = None

    @property
    def active(self) -> bool:
        return bool(self.coef.abs().sum() > 0)

    def _scaled(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """x = (q̃ − center)/scale (B, d) and its nearest point of the fitted box [−1, 1]^d."""
        x = (q - self.center.to(q)) / self.scale.to(q)
        return x, x.clamp(-1.0, 1.0)

    def _derivatives(self, x: Tensor, orders: Tensor) -> Tensor:
        """∂^orders of every monomial at x (B, d): `orders` (..., d) derivative orders (0, 1 or 2) per variable, one
        row per derivative wanted; returns (B, ..., P). All of them in one batched power and product: a rollout's
        Newton iterations call this a few times per step (one call per derivative was half the shooting's time at
        d = 4)."""
        E = self.exponents.to(x)  # (P, d)
        a = orders.to(x)[..., None, :]  # (..., 1, d)
        factor = torch.where(a == 0, torch.ones_like(E), torch.where(a == 1, E, E * (E - 1))).prod(-1)  # (..., P)
        powers = (E - a).clamp_min(0)  # (..., P, d)
        return (x.reshape(x.shape[0], *([1] * (powers.ndim - 1)), x.shape[1]) ** powers).prod(-1) * factor

    def _orders(self, x: Tensor, second: bool = False) -> Tensor:
        """The derivative orders of every ∂/∂x_i (d, d), or with `second` of every ∂²/∂x_i∂x_j (d, d, d)."""
        eye = torch.eye(x.shape[1], dtype=x.dtype, device=x.device)
        return eye[:, None, :] + eye[None, :, :] if second else eye

    def _coefficients(self, x: Tensor, coef: Optional[Tensor]) -> Tensor:
        """The coefficients (P,) or one row per code (B, P) (`coef`; None: the closure's own), in x's dtype."""
        if coef is None:
            return self.coef.to(x)
        if coef.ndim != 2 or coef.shape != (x.shape[0], len(self.coef)):
            raise ValueError(f"per-code closure coefficients must have shape ({x.shape[0]}, {len(self.coef)}), "
                             f"got {tuple(coef.shape)}")
        return coef.to(x)

    @staticmethod
    def _combine(basis: Tensor, coef: Tensor) -> Tensor:
        """Σ_p basis[..., p] θ_p (B, ...) of a basis (B, ..., P), for shared (P,) or per-code (B, P) coefficients."""
        if coef.ndim == 1:
            return basis @ coef
        return (basis * coef.reshape(coef.shape[0], *([1] * (basis.ndim - 2)), coef.shape[1])).sum(-1)

    def potential(self, q: Tensor, coef: Optional[Tensor] = None) -> Tensor:
        """ΔṼ (B,) at codes (B, d); `coef` (B, P): each code's own coefficients (None: the closure's)."""
        x, inside = self._scaled(q)
        coef = self._coefficients(x, coef)
        value = self._combine(self._derivatives(inside, torch.zeros_like(x[0])), coef)
        gap = x - inside
        if bool(gap.ne(0).any()):  # the continuation beyond the box: the gradient at its nearest point × the gap
            value = value + (self._combine(self._derivatives(inside, self._orders(x)), coef) * gap).sum(-1)
        return value

    def basis_gradients(self, q: Tensor) -> Tensor:
        """∂(monomial p)/∂q̃_i (B, d, P) at codes (B, d) inside the fitted box (what the fit solves with)."""
        x, _ = self._scaled(q)
        return self._derivatives(x, self._orders(x)) / self.scale.to(x)[:, None]

    def gradient(self, q: Tensor, coef: Optional[Tensor] = None) -> Tensor:
        """∇ΔṼ (B, d) at codes (B, d), the continuation's beyond the box: the polynomial's gradient at the nearest
        point of the box, plus, along each variable still inside it, the change of that gradient across the gap
        (NaN beyond a guard, :meth:`set_guard`); `coef` (B, P): each code's own coefficients (None: the closure's)."""
        x, inside = self._scaled(q)
        coef, gap = self._coefficients(x, coef), x - inside
        grad = self._combine(self._derivatives(inside, self._orders(x)), coef)  # (B, d)
        rows = gap.ne(0).any(-1).nonzero()[:, 0]  # the codes that left the box (a few of a rollout's, if any)
        if len(rows):  # there ∂²/∂x_i∂x_j × gap_j, j ≠ i, along each variable i still inside
            off, g = inside[rows], gap[rows]
            hess = self._combine(self._derivatives(off, self._orders(x, second=True)), coef if coef.ndim == 1
                                 else coef[rows])  # (R, d, d)
            hess = hess * (1.0 - torch.eye(x.shape[1], dtype=x.dtype, device=x.device))
            grad = grad.index_add(0, rows, (hess @ g[:, :, None])[..., 0] * (g == 0))
        return self._guarded(q, grad / self.scale.to(x))

    def set_guard(self, margin: Optional[float], span_floor: float = 0.0) -> None:
        """While set, the closure's force (:meth:`gradient`) is NaN at codes beyond the fitted range widened by
        `margin` of its span on each side (each code's span at least `span_floor` of the largest:
        :func:`floored_spans`): a rollout there ends as diverged, row by row (while the closure is refined by
        shooting, whose search would otherwise pay for trials that crawl off the codes, e.g. stiff implicit solves of
        the exact pullback). `margin` None: no guard."""
        if margin is None or self._fitted_range is None:
            self._guard = None
            return
        low, high = self._fitted_range
        pad = float(margin) * floored_spans(high - low, span_floor)
        self._guard = (low - pad, high + pad)

    def _guarded(self, q: Tensor, force: Tensor) -> Tensor:
        if self._guard is None:
            return force
        low, high = (b.to(q) for b in self._guard)
        outside = ((q < low) | (q > high)).any(-1, keepdim=True)
        return torch.where(outside, torch.full_like(force, float("nan")), force)

    def fit(self, codes: Tensor, residual: Tensor, regularizer: float, span_floor: float = 0.0) -> float:
        """Fit ∇ΔṼ(q̃) ≈ −r by ridge least squares (λ × the mean diagonal of the normal matrix); codes and residuals
        (B, d). Sets center and scale from the codes (their mean and largest deviation, each at least `span_floor` of
        the largest: :func:`floored_spans`). Returns the relative misfit ‖∇ΔṼ + r‖ / ‖r‖."""
        q, r = codes.detach().double().reshape(-1, codes.shape[-1]), residual.detach().double().reshape(-1, codes.shape[-1])
        self.center.copy_(q.mean(0))
        self.scale.copy_(floored_spans((q - q.mean(0)).abs().amax(0), span_floor).clamp_min(1e-6))
        self._fitted_range = (q.amin(0), q.amax(0))
        A = self.basis_gradients(q).reshape(-1, len(self.coef))  # rows (b, i), columns p
        y = -r.reshape(-1)
        normal = A.T @ A
        ridge = float(regularizer) * float(normal.diagonal().mean().clamp_min(1e-300))
        coef = torch.linalg.solve(normal + ridge * torch.eye(len(normal), dtype=normal.dtype), A.T @ y)
        self.coef.copy_(coef)
        return float((A @ coef - y).norm() / y.norm().clamp_min(1e-300))

    def reset(self) -> None:
        """No closure (ΔṼ = 0)."""
        self.coef.zero_()


class ClosedDynamics:
    """A reduced dynamics (exact or tabulated pullback) with a fitted potential closure ΔṼ added: forces −∇ΔṼ,
    energies + ΔṼ. Everything else (the mass, loads through ``controls``, table counters) is the base's.

    :meth:`set_row_coefficients` gives each row of the next rollouts its own closure coefficients (the shooting's
    finite-difference Jacobian as one batched rollout). They travel with the loads in ``controls``: the integrators
    hand ``controls`` row by row to the rows they solve (Newton's method on a subset), so the coefficients follow."""

    def __init__(self, base: Any, closure: PotentialClosure) -> None:
        self.__dict__.update(base=base, closure=closure, row_coef=None)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.base, name)

    def __setattr__(self, name: str, value: Any) -> None:  # e.g. controls: the base's forces read them
        if name == "controls" and self.row_coef is not None:  # (loads | coefficients), as `controls` gave them
            loads = getattr(self.base, "controls", None)  # the loads keep their columns (a row subset, say)
            columns = 0 if loads is None else loads.shape[1]
            self.__dict__["row_coef"] = value[:, columns:]
            if columns:
                self.base.controls = value[:, :columns]
            return
        setattr(self.base, name, value)

    @property
    def controls(self) -> Optional[Tensor]:
        """The base's loads (B, c), with the per-row closure coefficients (B, P) appended while they are set."""
        if self.row_coef is None:
            return self.base.controls  # an AttributeError where the base takes no loads: hasattr() says so
        loads = getattr(self.base, "controls", None)
        return self.row_coef if loads is None else torch.cat([loads.to(self.row_coef), self.row_coef], 1)

    def set_row_coefficients(self, coef: Optional[Tensor]) -> None:
        """Closure coefficients (B, P) for each row of the next rollouts, or None (the closure's own). Set the base's
        loads (if any) first: they keep their columns of ``controls``."""
        self.__dict__["row_coef"] = coef

    def acceleration(self, q: Tensor, v: Tensor, t: float = 0.0) -> Tensor:
        extra = self.closure.gradient(q, self.row_coef)
        return self.base.acceleration(q, v, t, extra_force=-extra)  # with the base's own M̃ (no second jet)

    def hamiltonian_derivatives(self, q: Tensor, p: Tensor, t: float = 0.0) -> tuple[Tensor, Tensor]:
        extra = self.closure.gradient(q, self.row_coef)
        v, force = self.base.hamiltonian_derivatives(q, p, t)
        return v, force - extra

    def potential_energy(self, q: Tensor) -> Tensor:
        return self.base.potential_energy(q) + self.closure.potential(q, self.row_coef)

    def energies(self, q: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        kinetic, potential = self.base.energies(q, v)
        extra = self.closure.potential(q.reshape(-1, q.shape[-1]), self.row_coef).reshape(potential.shape)
        return kinetic, potential + extra


def central_difference4(back2: Any, back1: Any, ahead1: Any, ahead2: Any, dt: float) -> Any:
    """The fourth-order central difference (f₋₂ − 8f₋₁ + 8f₊₁ − f₊₂) / (12 dt) of samples `dt` apart (arrays or
    tensors of one shape): the derivative at the middle sample, error O(dt⁴)."""
    return (back2 - 8.0 * back1 + 8.0 * ahead1 - ahead2) / (12.0 * dt)


def code_accelerations(velocities: Tensor, dt: float) -> Tensor:
    """q̃̈ at the inner samples 2 … T−3 of code velocities (n, T, d): the fourth-order central difference, (n, T−4, d)."""
    v = velocities
    return central_difference4(v[:, :-4], v[:, 1:-3], v[:, 3:-1], v[:, 4:], dt)


def equation_residual(dynamics: Any, codes: Tensor, velocities: Tensor, dt: float, t0: float = 0.0,
                      controls: Optional[Tensor] = None) -> tuple[Tensor, Tensor]:
    """r = M̃q̃̈ + c̃ + g̃ − τ̃ of encoded trajectories (codes, velocities (n, T, d), every `dt` [s] from `t0`, loads
    `controls` (n, c) or None) at their inner samples: (codes (n, T−4, d), r (n, T−4, d))."""
    accel = code_accelerations(velocities, dt)
    q, v = codes[:, 2:-2], velocities[:, 2:-2]
    out = []
    for k in range(q.shape[1]):  # one time per call: a forced scene's loads depend on t
        if controls is not None:
            dynamics.controls = controls.to(q)
        mass = dynamics.mass_matrix(q[:, k])
        model_accel = dynamics.acceleration(q[:, k], v[:, k], t0 + (k + 2) * dt)
        out.append(torch.einsum("bij,bj->bi", mass, accel[:, k] - model_accel))
    return q, torch.stack(out, 1)
