"""Where and why reduced rollouts diverged, and the substeps they took: the metrics and warnings of an evaluation."""
from __future__ import annotations

import logging
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from lnf.integrators.base import NOT_A_STEP_SIZE_PROBLEM, Trajectory
from lnf.reduced_model import ReducedModel
from lnf.evaluation_cost import chunked_energy
from lnf.quadrature import Quadrature, QuadratureRule

log = logging.getLogger("lnf.evaluation")


def divergence_steps(diverged_step: "Tensor | np.ndarray", non_finite: Optional[np.ndarray] = None,
                     record_every: int = 1) -> np.ndarray:
    """Per trajectory (n,), the integration step at which it diverged, −1 where it did not.

    A trajectory diverged where the integrator says so (`diverged_step` ≥ 0: its state became non-finite or
    exceeded the bound) or where a recorded quantity such as its energy is non-finite: `non_finite` (n, R)
    marks the recorded samples (every `record_every` steps); the earlier of the two counts.
    """
    steps = np.asarray(diverged_step.cpu() if isinstance(diverged_step, Tensor) else diverged_step,
                       dtype=np.int64).reshape(-1).copy()
    if non_finite is not None:
        bad = np.asarray(non_finite, dtype=bool).reshape(len(steps), -1)
        first = np.where(bad.any(-1), bad.argmax(-1) * int(record_every), -1)
        steps = np.where((first >= 0) & ((steps < 0) | (first < steps)), first, steps)
    return steps


@torch.no_grad()
def initial_state_causes(model: ReducedModel, dynamics: object, q0: Tensor, v0: Tensor, rows: "list[int] | np.ndarray",
                         quadrature: "Quadrature | QuadratureRule | None" = None) -> dict[int, str]:
    """For the trajectories `rows` (diverged ones), what is already non-finite at their initial reduced state
    (q̃0, q̃̇0) (B, d), by trajectory: the state itself (ρ̃ of the initial fields), the potential Ṽ(q̃0) (the scene's
    potential), the kinetic energy T̃ (the scene's mass density), or the acceleration of `dynamics` (after a rollout
    has set its controls). Trajectories with a finite start are left out: they diverged on the way."""
    rows = [int(r) for r in rows]
    if not rows:
        return {}
    causes: dict[int, str] = {}
    state_ok = torch.isfinite(q0).all(-1) & torch.isfinite(v0).all(-1)
    safe_q = torch.where(state_ok[:, None], q0, torch.zeros_like(q0))
    safe_v = torch.where(state_ok[:, None], v0, torch.zeros_like(v0))
    try:
        kin, pot = chunked_energy(model, safe_q, safe_v, quadrature)
    except Exception:  # noqa: BLE001 - a diagnosis only
        kin = pot = torch.zeros(len(q0), dtype=q0.dtype, device=q0.device)
    try:
        acc = dynamics.acceleration(safe_q, safe_v, 0.0)
        acc_ok = torch.isfinite(acc).all(-1)
    except Exception:  # noqa: BLE001
        acc_ok = torch.ones(len(q0), dtype=torch.bool, device=q0.device)
    for r in rows:
        if not bool(state_ok[r]):
            causes[r] = ("its initial reduced state (q̃0, q̃̇0) is non-finite: ρ̃ of the initial fields gave NaN or inf "
                         "(the initial state, the scene's fields there, or the model's reduction)")
        elif not bool(torch.isfinite(pot[r])):
            causes[r] = (f"the potential energy Ṽ(q̃0) is {float(pot[r]):g} at its initial state: the scene's "
                         f"potential is non-finite there")
        elif not bool(torch.isfinite(kin[r])):
            causes[r] = (f"the kinetic energy T̃(q̃0, q̃̇0) is {float(kin[r]):g} at its initial state: the scene's mass "
                         f"density (or the model's φ) is non-finite there")
        elif not bool(acc_ok[r]):
            causes[r] = ("the acceleration is non-finite at its initial state: the pulled-back potential or mass "
                         "(the scene's potential or mass density, or the model) is NaN or inf there")
    return causes


def divergence_metrics(steps: np.ndarray, dt: float, t0: float = 0.0, suffix: str = "",
                       label: str = "rollout", causes: Optional[dict[int, str]] = None,
                       diagnoses: Optional[dict[int, str]] = None) -> dict[str, float]:
    """`diverged_count`, `diverged_fraction`, `first_divergence_step` and `first_divergence_time` [s] (+ `suffix`)
    from per-trajectory divergence steps (n,) (−1: stayed finite; see :func:`divergence_steps`).

    The first step and time are the earliest over the trajectories; both are −1.0 when none diverged (JSON has
    no NaN). A divergence is also logged as a warning (logger ``lnf.evaluation``) naming the `label`ed rollout;
    trajectories in `causes` (see :func:`initial_state_causes`) were non-finite at their initial state already, and
    the warning names that cause instead of suggesting a smaller step; trajectories in `diagnoses` (the
    integrator's :func:`lnf.integrators.base.divergence_diagnosis`, ``Trajectory.extra["divergence_causes"]``) diverged
    on the way, and the warning says why (a stiff step, or dynamics that run away at a resolved step).
    """
    steps = np.asarray(steps).reshape(-1)
    hit = steps >= 0
    count = int(hit.sum())
    first = int(steps[hit].min()) if count else -1
    when = float(t0 + first * dt) if count else -1.0
    if count:
        which = np.flatnonzero(hit).tolist()
        causes = {r: c for r, c in (causes or {}).items() if r in which}
        on_the_way = [r for r in which if r not in causes]
        hints = []
        for cause in dict.fromkeys(causes.values()):
            rows = [r for r, c in causes.items() if c == cause]
            hints.append(f"trajectories {rows[:10]}{' …' if len(rows) > 10 else ''}: {cause}")
        if causes:
            hints.append(NOT_A_STEP_SIZE_PROBLEM)
        diagnoses = {r: d for r, d in (diagnoses or {}).items() if r in on_the_way}
        for text in list(dict.fromkeys(diagnoses.values()))[:3]:
            rows = [r for r, d in diagnoses.items() if d == text]
            hints.append(f"trajectories {rows[:10]}{' …' if len(rows) > 10 else ''}: {text}")
        on_the_way = [r for r in on_the_way if r not in diagnoses]
        if on_the_way:
            hints.append(f"{'trajectories ' + str(on_the_way[:10]) + (' …' if len(on_the_way) > 10 else '') + ': ' if causes or diagnoses else ''}"
                         f"try a smaller dt, integrator.substeps or another integrator")
        log.warning("%s: %d of %d trajectories diverged (non-finite or exploding state or energy), the first at "
                    "step %d (t = %.6g s, dt = %g s); trajectories %s%s. %s.", label, count, len(steps), first, when,
                    dt, which[:10], " …" if len(which) > 10 else "", ". ".join(h[:1].upper() + h[1:] for h in hints))
    return {f"diverged_count{suffix}": float(count), f"diverged_fraction{suffix}": count / max(len(steps), 1),
            f"first_divergence_step{suffix}": float(first), f"first_divergence_time{suffix}": when}


def substeps_metrics(traj: Trajectory, dt: float, label: str, suffix: str = "") -> dict[str, float]:
    """`substeps<suffix>`: the integration steps per step dt a rollout ended with, where the integrator's automatic
    substeps raised them (a step stiff against the fastest reduced frequency), logged with where; {} otherwise."""
    info = traj.extra.get("substeps")
    if not info:
        return {}
    at = info["raised_at_steps"]
    log.info("%s: the step dt = %g s was stiff against the fastest reduced frequency: %d substeps from the start, %d "
             "at the end%s (integrator.max_substeps caps them; integrator.substeps sets the least)", label, dt,
             info["initial"], info["final"], f", raised at step{'s' if len(at) > 1 else ''} "
             f"{', '.join(map(str, at[:5]))}{' …' if len(at) > 5 else ''}" if at else "")
    return {f"substeps{suffix}": float(info["final"])}
