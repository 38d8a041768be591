"""Implicit midpoint rule on (q̃, p̃ = M̃ q̃̇): symplectic and symmetric, bounded energy error.

For H(q̃, p̃) = ½ p̃ᵀ M̃(q̃)⁻¹ p̃ + Ṽ(q̃) a step solves
    q̃₁ = q̃₀ + h ∂H/∂p̃(q̃ₘ, p̃ₘ),   p̃₁ = p̃₀ − h ∂H/∂q̃(q̃ₘ, p̃ₘ),   (·)ₘ = ((·)₀ + (·)₁)/2,
with ∂H/∂p̃ = q̃̇ = M̃⁻¹p̃ and ∂H/∂q̃ = g̃ − ∂T̃/∂q̃|_{q̃̇}, by fixed-point iteration from the previous step's
increments; rows it does not converge in `max_iter` iterations, on which it stops contracting, or which it would
take more than `NEWTON_AFTER` further iterations to converge at the slow rate it contracts (a step that is stiff against
the fastest reduced frequency, as pulled-back elastic dynamics at d ≥ 2 are), are solved by Newton's method
(`newton`, on by default), and a trajectory that neither converges is reported as diverged.
`order=4` (the default, as in conf/integrator/implicit_midpoint.yaml) composes three midpoint steps
(Suzuki–Yoshida triple jump): still symplectic, fourth order, energy error O(h⁴); `order=2` is one plain
midpoint step per step.
"""
from __future__ import annotations


import torch
from torch import Tensor

from lnf.integrators.base import FixedStepIntegrator, central_jacobian
from lnf.utils import require

#: the fixed-point iteration hands a solve to Newton's method once a row it has not converged contracts slowly (each
#: correction more than NEWTON_SLOW_RATE of the last, from its third iteration on) and would need more than
#: NEWTON_AFTER further iterations at that rate: on the cantilevers' tables, where the substeps keep h·ω_max near 1,
#: it contracted at ~0.5 and took 15 iterations a solve, where Newton's method with the rollout's kept Jacobian takes
#: two or three. A fast contraction (the pendulum's) keeps the fixed-point iteration and its numbers, and so does a
#: system of more than NEWTON_MAX_DIM coordinates (a full-order model: its Jacobian would cost 4d evaluations)
NEWTON_SLOW_RATE, NEWTON_AFTER, NEWTON_MAX_DIM = 0.25, 6, 16


class ImplicitMidpoint(FixedStepIntegrator):
    name = "implicit_midpoint"
    stiff_step = 1.0  # h·ω_max: the fixed-point iteration contracts; the phase error of that mode stays under 8 %

    def __init__(self, substeps: int = 1, order: int = 4, tol: float = 1e-12, max_iter: int = 50,
                 max_abs: float = 1e6, newton: bool = True, max_substeps: int = 64) -> None:
        super().__init__(substeps=substeps, max_abs=max_abs, max_substeps=max_substeps)
        if order not in (2, 4):
            raise ValueError(f"integrator.order must be 2 or 4 for implicit_midpoint, got {order!r}")
        self.order, self.tol, self.max_iter = order, require("integrator.tol", tol), require("integrator.max_iter", max_iter)
        if order == 2:
            self.fractions = [1.0]
        else:
            c = 2.0 ** (1.0 / 3.0)
            g1 = 1.0 / (2.0 - c)
            self.fractions = [g1, -c * g1, g1]
        self.iterations: list[int] = []  # fixed-point iterations per midpoint solve (diagnostics)
        self.newton = bool(newton)
        self.newton_iter = 20  # Newton converges quadratically, a reused J linearly at rate ≤ 0.1: else diverging
        self.newton_solves = 0  # midpoint solves that needed Newton's method (diagnostics)
        self.jacobians = 0  # Jacobians ∂f/∂z computed for Newton's method (diagnostics; each costs 4d evaluations)
        self._stiff = False
        self._jacobian: "Tensor | None" = None  # (B, 2d, 2d): the last J of each row, reused by the next solves

    def __repr__(self) -> str:
        return f"ImplicitMidpoint(order={self.order}, substeps={self.substeps}, tol={self.tol:g})"

    def _to_internal(self, dynamics, q: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        if not hasattr(dynamics, "hamiltonian_derivatives"):
            raise ValueError(f"{type(dynamics).__name__} has no Hamiltonian (it is not the pullback of a Lagrangian), "
                             "so the symplectic implicit midpoint rule does not apply; use integrator=rk4 or dopri5")
        p = dynamics.momentum(q, v)
        self._stiff = False  # set once a step of this rollout needed Newton's method
        self._jacobian = None
        # the last two entries carry the previous step's rates (q̃̇ₘ, ṗₘ): the predictor of the next solve
        return q, p, v.clone(), torch.zeros_like(p)

    def _substeps_raised(self) -> None:
        self._stiff = False  # the smaller step may not need Newton's method: start from the fixed-point iteration again

    def _to_qv(self, dynamics, state: tuple[Tensor, ...]) -> tuple[Tensor, Tensor]:
        q, p = state[0], state[1]
        return q, dynamics.velocity(q, p)

    def _bad(self, *xs: Tensor) -> Tensor:
        return super()._bad(xs[0], xs[1])

    def _midpoint(self, dynamics, q: Tensor, p: Tensor, rq: Tensor, rp: Tensor, h: float, t: float):
        """Solve one midpoint step; returns rates (Δq/h, Δp/h). Rows that do not converge become NaN.

        Fixed-point iteration first (cheap, converges when h is small against the fastest time scale);
        rows it leaves unconverged after `max_iter`, or would take more than :data:`NEWTON_AFTER` more iterations
        to converge, go to Newton's method (if `newton`), whose Jacobian comes from central differences of the
        dynamics (4d evaluations, relative error about eps^(2/3)); it starts from the last iterate where the
        iteration contracted, from the predictor where it did not.
        """
        tol = max(self.tol, 16 * torch.finfo(q.dtype).eps) * (1.0 + q.abs().amax(-1) + p.abs().amax(-1))
        guess = (rq, rp)  # Newton restarts from the predictor, not from a fixed-point iterate that ran away
        first = last = None
        limit = 3 if self._stiff else self.max_iter  # a stiff rollout: Newton after 3 iterations, not 50
        for it in range(1, limit + 1):
            vm, force = dynamics.hamiltonian_derivatives(q + 0.5 * h * rq, p + 0.5 * h * rp, t + 0.5 * h)
            err = torch.maximum((vm - rq).abs().amax(-1), (force - rp).abs().amax(-1)) * abs(h)
            rq, rp = vm, force
            if bool((err <= tol).all()):
                self.iterations.append(it)
                return rq, rp
            first = err if first is None else first
            # a stiff step (h times the fastest reduced frequency beyond ~1): the iteration does not contract, so
            # Newton's method takes these rows at once instead of after max_iter wasted evaluations
            if self.newton and it >= 10 and bool((~(err <= tol) & ~(err < first)).any()):
                break
            if self.newton and it >= 3 and q.shape[-1] <= NEWTON_MAX_DIM and self._slow(err, last, tol):
                # contracting, slowly: Newton goes on from these iterates (from the predictor where they did not)
                contracting = (err < last)[:, None]
                guess = (torch.where(contracting, rq, guess[0]), torch.where(contracting, rp, guess[1]))
                break
            last = err
        self.iterations.append(it)
        failed = ~(err <= tol)
        if self.newton:
            self._stiff = True
            rq, rp, failed = self._newton(dynamics, q, p, *guess, h, t, tol, failed, fallback=(rq, rp))
        nan = torch.tensor(float("nan"), dtype=q.dtype, device=q.device)
        return torch.where(failed[:, None], nan, rq), torch.where(failed[:, None], nan, rp)

    @staticmethod
    def _slow(err: Tensor, last: Tensor, tol: Tensor) -> bool:
        """Whether a row not converged (err > tol, (B,)) contracts at a rate err / last over NEWTON_SLOW_RATE and
        would need more than NEWTON_AFTER further fixed-point iterations at it."""
        rate = (err / last.clamp_min(1e-300)).clamp(1e-6, 1.0 - 1e-6)
        left = torch.log(tol / err.clamp_min(1e-300)) / torch.log(rate)
        return bool((~(err <= tol) & (rate > NEWTON_SLOW_RATE) & (left > NEWTON_AFTER)).any())

    def _newton(self, dynamics, q: Tensor, p: Tensor, rq: Tensor, rp: Tensor, h: float, t: float, tol: Tensor,
                rows: Tensor, fallback: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """Newton's method on r = f(z₀ + h r / 2) from the guess (rq, rp) for the rows `rows` (B,).

        The Jacobian J = ∂f/∂z (2d × 2d per row, from central differences: 4d evaluations) is kept from the last
        solve of the rollout and reused (a simplified, "chord" Newton: one evaluation per iteration) for as long
        as the iterates contract fast (each correction at most 0.1 of the last); a row whose iteration slows is
        given a fresh J at its current iterate. J does not depend on h, so one J serves the substeps and the three sizes of
        the order-4 composition. Returns the rates (`fallback` in the other rows) and the rows still failing."""
        idx = rows.nonzero().flatten()
        d = q.shape[-1]
        z0 = torch.cat([q[idx], p[idx]], -1)
        controls = getattr(dynamics, "controls", None)
        if controls is not None:
            dynamics.controls = controls[idx]
        start = torch.cat([rq[idx], rp[idx]], -1)
        r = torch.where(torch.isfinite(start), start, torch.zeros_like(start))

        def rates(z: Tensor) -> Tensor:
            vm, force = dynamics.hamiltonian_derivatives(z[:, :d], z[:, d:], t + 0.5 * h)
            return torch.cat([vm, force], -1)

        eye = torch.eye(2 * d, dtype=q.dtype, device=q.device)
        eps = torch.finfo(q.dtype).eps ** (1.0 / 3.0)  # central differences: truncation and rounding balanced
        cache = self._jacobian if self._jacobian is not None and self._jacobian.shape[0] == q.shape[0] else None
        if cache is None:
            jac = torch.zeros(len(idx), 2 * d, 2 * d, dtype=q.dtype, device=q.device)
            stale = torch.ones(len(idx), dtype=torch.bool, device=q.device)  # rows whose J is computed now
        else:
            jac = cache[idx]
            stale = ~torch.isfinite(jac).flatten(1).all(-1)
        err = torch.full((len(idx),), float("inf"), dtype=q.dtype, device=q.device)
        try:
            for _ in range(self.newton_iter):
                z = z0 + 0.5 * h * r
                value = rates(z)
                if bool(stale.any()):
                    # ∂f/∂z by central differences through torch's own kernels (forward-mode AD, torch.func.jvp,
                    # went through Python decompositions, 20x slower on a d = 2 elastic pullback)
                    rows_j = stale.nonzero().flatten()
                    zj, rj = z0[rows_j], r[rows_j]
                    if controls is not None:
                        dynamics.controls = controls[idx][rows_j]
                    # steps in r of eps·(1 + |r|), i.e. in z of (h/2)·eps·(1 + |r|): the scale of the step's own
                    # increments (a step of eps·|z| in z is a secant far too wide in float32); J = (2/h) ∂f/∂r
                    jac[rows_j] = central_jacobian(lambda x: rates(zj + 0.5 * h * x), rj,
                                                   (eps * (1.0 + rj.abs().amax(-1, keepdim=True))).expand_as(rj)
                                                   ) * (2.0 / h)
                    if controls is not None:
                        dynamics.controls = controls[idx]
                    self.jacobians += 1
                    stale = torch.zeros_like(stale)
                delta = torch.linalg.solve(eye - 0.5 * h * jac, value - r)
                r = r + delta
                last, err = err, delta.abs().amax(-1) * abs(h)
                done = err <= tol[idx]
                if bool(done.all()) or not bool(torch.isfinite(r).any()):
                    break
                stale = ~done & ~(err <= 0.1 * last)  # J too far from this iterate's: the iteration slowed
        finally:
            if controls is not None:
                dynamics.controls = controls
        ok = torch.isfinite(r).all(-1) & (err <= tol[idx])
        if cache is None:
            cache = torch.full((q.shape[0], 2 * d, 2 * d), float("nan"), dtype=q.dtype, device=q.device)
        cache[idx] = jac
        self._jacobian = cache
        rq, rp, still = fallback[0].clone(), fallback[1].clone(), rows.clone()
        rq[idx], rp[idx] = r[:, :d], r[:, d:]
        still[idx] = ~ok
        self.newton_solves += 1
        return rq, rp, still

    def step(self, dynamics, state: tuple[Tensor, ...], h: float, t: float) -> tuple[Tensor, ...]:
        q, p, rq, rp = state
        for frac in self.fractions:
            hf = frac * h
            rq, rp = self._midpoint(dynamics, q, p, rq, rp, hf, t)
            q, p = q + hf * rq, p + hf * rp
            t = t + hf
        return q, p, rq, rp
