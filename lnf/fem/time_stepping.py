"""Time stepping of a finite-element body, M ü = f(u, t) − α M u̇ with lumped M, on the free degrees of freedom.

- :func:`verlet`: velocity Verlet (explicit, symplectic; the damping as an exact conformal factor), batched over
  trajectories; stable below the CFL limit (:meth:`lnf.fem.body.ElasticBody.stable_time_step`).
- :func:`implicit_midpoint`: the implicit midpoint rule (symplectic, second order, unconditionally stable for
  linear elasticity) solved by Newton's method with the exact tangent stiffness, so that steps far above the CFL
  limit are possible; one trajectory after another (each Newton step assembles and factorises K).

Both sample the trajectory at uniformly spaced `times` with an integer number of substeps per sample.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from lnf.fem.body import ElasticBody

#: f(u (B, nn, d), t, b) → (B, nn, d) [N]: the conservative and applied forces (no damping) at time t [s];
#: b: the trajectories' indices (B,) into the caller's batch, for per-trajectory loads
ForceFn = Callable[[np.ndarray, float, np.ndarray], np.ndarray]


def _substeps(times: np.ndarray, time_step: float) -> tuple[int, float]:
    if len(times) < 2:
        return 1, 0.0
    sample = float(times[1] - times[0])
    n = max(1, math.ceil(sample / time_step - 1e-9))
    return n, sample / n


def verlet(body: ElasticBody, force: ForceFn, u: np.ndarray, v: np.ndarray, times: np.ndarray, time_step: float,
           damping: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) (B, T, nn, d) at `times` from u, v (B, nn, d) at times[0], velocity Verlet at ≤ `time_step` [s]."""
    times = np.asarray(times, dtype=np.float64)
    u, v = np.array(u, dtype=np.float64), np.array(v, dtype=np.float64)
    out_u, out_v = np.empty((len(u), len(times), *u.shape[1:])), np.empty((len(u), len(times), *u.shape[1:]))
    out_u[:, 0], out_v[:, 0] = u, v
    substeps, h = _substeps(times, time_step)
    decay = math.exp(-0.5 * damping * h)
    mass = body.nodal_mass[None, :, None]
    batch = np.arange(len(u))
    t = float(times[0])

    def acceleration(u: np.ndarray, t: float) -> np.ndarray:
        acc = force(u, t, batch) / mass
        acc[:, body.clamped] = 0.0
        return acc

    acc = acceleration(u, t)
    for k in range(1, len(times)):
        for _ in range(substeps):
            v = decay * v + 0.5 * h * acc
            u = u + h * v
            t += h
            acc = acceleration(u, t)
            v = decay * (v + 0.5 * h * acc)
        if not np.isfinite(u).all():
            raise FloatingPointError(f"velocity Verlet diverged at t = {t:.4g} s with time step {h:.3g} s, above the "
                                     f"body's stability limit (about {body.stable_time_step():.3g} s): use a smaller "
                                     "time step or the implicit midpoint rule")
        out_u[:, k], out_v[:, k] = u, v
    return out_u, out_v


def implicit_midpoint(body: ElasticBody, force: ForceFn, u: np.ndarray, v: np.ndarray, times: np.ndarray,
                      time_step: float, damping: float = 0.0, tol: float = 1e-9, max_newton: int = 25
                      ) -> tuple[np.ndarray, np.ndarray, int]:
    """(u, v) (B, T, nn, d) at `times` and the most Newton iterations a step took, by the implicit midpoint rule:

        u₁ = u₀ + h v̄,  M (v₁ − v₀)/h = f(ū, t + h/2) − α M v̄,  ū = (u₀ + u₁)/2, v̄ = (v₀ + v₁)/2.

    With Δ = u₁ − u₀ (v̄ = Δ/h): R(Δ) = M (2/h²)(Δ − h v₀) + α M Δ/h − f(u₀ + Δ/2) = 0, Jacobian
    (2/h² + α/h) M + ½ K(ū); Newton stops when ‖R‖∞ ≤ `tol` × (‖f‖∞ + ‖M v₀/h‖∞ + 1e-300)."""
    times = np.asarray(times, dtype=np.float64)
    u, v = np.array(u, dtype=np.float64), np.array(v, dtype=np.float64)
    B, nn, d = u.shape
    out_u, out_v = np.empty((B, len(times), nn, d)), np.empty((B, len(times), nn, d))
    out_u[:, 0], out_v[:, 0] = u, v
    substeps, h = _substeps(times, time_step)
    free = body.free_dofs
    mass = np.repeat(body.nodal_mass, d)  # node-major, as the dofs
    diag = sp.diags((2.0 / h**2 + damping / h) * mass[free]) if h > 0 else None
    held = np.repeat(body.clamped, d)
    worst = 0
    for b in range(B):
        index = np.array([b])
        ub, vb, t = u[b].reshape(-1), v[b].reshape(-1).copy(), float(times[0])
        vb[held] = 0.0
        for k in range(1, len(times)):
            for _ in range(substeps):
                delta = h * vb
                delta[held] = 0.0
                for it in range(max_newton + 1):
                    mid = (ub + 0.5 * delta).reshape(1, nn, d)
                    f = force(mid, t + 0.5 * h, index).reshape(-1)
                    residual = (mass * ((2.0 / h**2) * (delta - h * vb) + damping * delta / h) - f)[free]
                    scale = np.abs(f[free]).max() + np.abs(mass * vb / h)[free].max() + 1e-300
                    if np.abs(residual).max() <= tol * scale:
                        break
                    if it == max_newton:
                        raise FloatingPointError(
                            f"implicit midpoint: Newton did not converge in {max_newton} iterations at t = {t:.4g} s "
                            f"(time step {h:.3g} s, residual {np.abs(residual).max():.3g} N): use a smaller time step")
                    K = body.tangent_stiffness(mid[0])[free][:, free]
                    delta[free] -= spla.spsolve((diag + 0.5 * K).tocsc(), residual)
                worst = max(worst, it)
                vb = 2.0 * delta / h - vb
                ub = ub + delta
                t += h
            out_u[b, k], out_v[b, k] = ub.reshape(nn, d), vb.reshape(nn, d)
    return out_u, out_v, worst
