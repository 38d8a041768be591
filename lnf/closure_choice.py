"""Fitting a model's potential closure ΔṼ after training (lnf/closure.py): the residual of the pulled-back equations
along the encoded training trajectories, one ridge fit per candidate regularizer, the best of them refined by
shooting (the coefficients whose rollouts follow the encoded training codes over the training window), and the
choice among them (or none) by validation rollouts. Used by lnf.train, lnf.evaluate [closure_degree=p] and the
studies."""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import time
from typing import Any

import numpy as np
import torch
from scipy.optimize import least_squares

from lnf.baselines.latent_mlp import latent_trajectories
from lnf.closure import CLOSURE_MAX_TERMS, ClosedDynamics, equation_residual, floored_spans
from lnf.evaluation_pipeline import EvaluationData, EvaluationSpec, evaluate_model

log = logging.getLogger("lnf.closure")


#: the closure's candidate regularizers (ridge λ, relative to the normal matrix's mean diagonal)
CLOSURE_REGULARIZERS = (1e-8, 1e-5, 1e-2)
CLOSURE_VAL_TRAJECTORIES = 8
#: the training trajectories (evenly spaced) whose rollouts the shooting refinement fits: 16 on a table whose
#: evaluation costs at most SHOOTING_TABLE_WORK multiply-adds a row (its coefficients: terms × outputs; a 128² table
#: of M̃ and Ṽ at d = 2, the soft body's, is 196 608; the cantilevers' 64² a quarter), 4 where a row costs more: the
#: exact pullback (a jet per step) or a larger table (the soft body's d = 4 one, read as 12 288 terms of 55 outputs:
#: 676 000; its first shooting vector took 958 s on 16 trajectories); and its Levenberg–Marquardt iterations per
#: term in each stage by default (``evaluation.closure_shooting_iterations``)
SHOOTING_TRAJECTORIES, SHOOTING_TRAJECTORIES_EXACT, SHOOTING_TABLE_WORK = 16, 4, 128 ** 2 * 3 * 4
SHOOTING_ITERATIONS_PER_TERM = EvaluationSpec.closure_shooting_iterations
#: a stage's budget counts at most this many terms (d = 2 at degree 4): with more (34 at d = 3, 69 at d = 4, where
#: model.closure_max_terms is lifted) it stays
#: at iterations × 15² coefficient vectors, so fewer Levenberg–Marquardt iterations, each a rollout of terms + 1
#: vectors (20 · 35² = 24 500 at d = 3 before: the actuated cantilever's d = 3 shooting ran past 47 min unfinished)
SHOOTING_BUDGET_TERMS = CLOSURE_MAX_TERMS
#: a shooting trial whose rollout leaves the training codes by more than this fraction of their span ends there
SHOOTING_GUARD_MARGIN = 1.0
#: the shooting first fits windows of this many samples (multiple shooting: each window starts from the encoded
#: state), then the whole training window from there
SHOOTING_WINDOW = 10
#: a shooting stage stops once its best gap has shrunk by less than SHOOTING_STALL (relative) over its last
#: SHOOTING_STALL_ITERATIONS Levenberg–Marquardt iterations: scipy's own tolerances (10⁻⁸) would go on to the budget
#: (the cantilever's d = 4 windows: 0.00156 → 0.00153 spreads over 5 iterations of 3 min, with 270 more allowed)
SHOOTING_STALL, SHOOTING_STALL_ITERATIONS = 0.01, 3
#: a shooting stage logs its progress at most this often [s] (the log only: the search does not depend on it)
SHOOTING_LOG_SECONDS = 60.0


def fit_closure(model: Any, datamodule: Any, spec: Any) -> dict[str, float]:
    """Fit the model's potential closure ΔṼ (lnf/closure.py) after training: the pulled-back equations' residual
    along the encoded training trajectories, a ridge fit per regularizer of :data:`CLOSURE_REGULARIZERS` (and, where
    the model's codes share one unit, per code scale: each code's own span, or floored at its `code_span_floor`), and the
    one (or none: the pure pullback) whose rollouts of the first validation trajectories have the smallest field
    error within the training horizon (rolled out that far only: :meth:`EvaluationData.within_horizon`). The
    residual fit with the best validation error (chosen or not) is then refined by shooting (:func:`shoot_closure`,
    `spec.closure_shooting_iterations` iterations per term in each stage; none at 0) and the refinement is a
    candidate of its own. `spec`: the test's EvaluationSpec (its
    integrator, decoding and shooting budget)."""
    start = time.perf_counter()
    closure = model.closure
    model.eval()
    train, val = datamodule.split("train"), datamodule.split("val")
    data = EvaluationData.of_split(val, model.scene, CLOSURE_VAL_TRAJECTORIES).within_horizon()  # in-horizon errors
    check = dataclasses.replace(spec, split="val", label="closure choice: validation rollout", long_steps=0,
                                figures=0, keep_fields=0, progress=False)

    def val_error() -> float:
        with torch.no_grad():
            err = evaluate_model(model, data, check).metrics["field_rel_l2/in_horizon/median"]
        return err if math.isfinite(err) else math.inf

    closure.reset()
    best = (val_error(), 0.0, 0.0)  # (error, λ, misfit); λ = 0: none
    pullback_error = best[0]
    if getattr(model, "latent_dynamics", None) is not None:  # the black box's rollouts never read a closure
        log.info("potential closure: none (%s rolls out learned latent dynamics)", type(model).__name__)
        return _record(best, pullback_error, False, time.perf_counter() - start)
    points, values, velocities = (torch.as_tensor(a) for a in datamodule.observations("train"))
    loads = train.loads(model.scene)  # the scene's loads where the file stores none (the actuated cantilever)
    controls = None if loads is None else torch.as_tensor(loads)
    with torch.no_grad():
        q, v = latent_trajectories(model, points, values, velocities)
        codes, residual = equation_residual(model.lagrangian_dynamics(), q, v, datamodule.dt,
                                            float(train.times[0]), controls)
    # candidates: each regularizer with each code scale the model allows (each code's own span, and where the codes
    # share one unit also its floor, CODE_SPAN_FLOOR of the largest: lnf/closure.py); a candidate is (validation
    # error, λ, misfit, span floor, coefficients); its scale is refitted from (λ, floor) in milliseconds when needed
    start_from: tuple = (math.inf, 0.0, 0.0, 0.0, None)  # the best residual fit, chosen or not
    chosen: tuple = (*best, 0.0, None)  # the best candidate; coefficients None: the pure pullback
    shot = False
    flat = codes.reshape(-1, codes.shape[-1])
    spans = (flat - flat.mean(0)).abs().amax(0)
    floor = float(getattr(model, "code_span_floor", 0.0))
    # the floored scale only where it raises some code's span (never at d = 1: the two fits would be one)
    floors = (0.0, floor) if floor > 0 and bool((floored_spans(spans, floor) > spans).any()) else (0.0,)
    for floor in floors:
        for lam in CLOSURE_REGULARIZERS:
            misfit = closure.fit(codes, residual, lam, floor)
            err = val_error()
            log.info("closure λ = %.0e%s: misfit %.3f of the residual, validation field error %.4g in the horizon",
                     lam, f", codes' spans floored at {floor:g} of the largest" if floor else "", misfit, err)
            candidate = (err, lam, misfit, floor, closure.coef.clone())
            if err < chosen[0]:
                chosen = candidate
            if start_from[4] is None or err < start_from[0]:
                start_from = candidate

    def restore(candidate: tuple) -> None:
        closure.fit(codes, residual, candidate[1], candidate[3])  # its centre and scale
        closure.coef.copy_(candidate[4])

    iterations = int(getattr(spec, "closure_shooting_iterations", SHOOTING_ITERATIONS_PER_TERM))
    if iterations > 0:
        # shooting starts from a residual fit even where the pure pullback won: from zero the search stalls in a
        # local minimum of the phase (soft body: misfit 0.051 → 0.051; from the residual fit 0.074 → 0.012; at
        # d = 2, multiple shooting from zero 0.047 → 0.047, from the residual fit 4.17 → 0.028)
        restore(start_from)
        cost = shoot_closure(model, q, v, datamodule.dt, controls, spec.integrator, float(train.times[0]),
                             iterations)
        # unchanged coefficients (the search found nothing better) keep their validation error: no second rollout
        err = val_error() if cost[1] < cost[0] else start_from[0]
        log.info("closure by shooting from λ = %.0e: training-window misfit %.3g → %.3g of the codes' spread, "
                 "validation field error %.4g in the horizon", start_from[1], *cost, err)
        if err < chosen[0]:
            chosen, shot = (err, *start_from[1:4], closure.coef.clone()), True
    else:
        log.info("closure shooting: none (closure_shooting_iterations = 0)")
    closure.reset()
    if chosen[4] is not None:
        restore(chosen)
    best = chosen[:3]
    seconds = time.perf_counter() - start
    log.info("potential closure: %s (validation field error %.4g in the horizon, the pure pullback's %.4g), %.1f s",
             f"λ = {best[1]:.0e}{', refined by shooting' if shot else ''}, {len(closure.coef)} terms"
             f"{f', spans floored at {chosen[3]:g}' if chosen[3] else ''}" if best[1] > 0
             else "none (the pure pullback is best)", best[0], pullback_error, seconds)
    return _record(best, pullback_error, shot, seconds, chosen[3])


def _record(best: tuple[float, float, float], pullback_error: float, shot: bool, seconds: float,
            span_floor: float = 0.0) -> dict[str, float]:
    """What metrics.json records of the choice: `best` is (validation error, λ (0: none), residual misfit);
    `span_floor` the chosen closure's floor of the codes' spans (0: each code's own)."""
    return {"closure_regularizer": best[1], "closure_val_error": best[0], "closure_pullback_val_error": pullback_error,
            "closure_misfit": best[2], "closure_shooting": float(shot), "closure_seconds": seconds,
            "closure_span_floor": span_floor}


class _BudgetSpent(Exception):
    """A shooting stage rolled out as often as its budget allows: the search stops there."""


class _Stalled(Exception):
    """A shooting stage's best gap stopped shrinking (:data:`SHOOTING_STALL`): the search stops there."""


def shoot_closure(model: Any, codes: torch.Tensor, velocities: torch.Tensor, dt: float,
                  controls: "torch.Tensor | None", integrator: Any, t0: float = 0.0,
                  iterations_per_term: int = SHOOTING_ITERATIONS_PER_TERM) -> tuple[float, float]:
    """Refine the model's closure coefficients in place by shooting: Levenberg–Marquardt (scipy) on the gap between
    the closed dynamics' rollouts from encoded training states (q̃, q̃̇) and the encoded codes `codes` (n, T, d, every
    `dt` [s] from `t0`), in units of the codes' spread, on :data:`SHOOTING_TRAJECTORIES` evenly spaced trajectories
    (:data:`SHOOTING_TRAJECTORIES_EXACT` where the dynamics are not a table or a table that costs more than
    :data:`SHOOTING_TABLE_WORK` multiply-adds a row), under the evaluation's `integrator`,
    with a budget of `iterations_per_term` × (m + 1)² coefficient vectors rolled out in each stage, m = min(terms,
    :data:`SHOOTING_BUDGET_TERMS`), or sooner once it stalls (:data:`SHOOTING_STALL`): an iteration of
    Levenberg–Marquardt rolls out terms + 1 vectors for its finite-difference Jacobian (one batched rollout: each
    block of rows its own coefficients) and one for its trial, so up to that many terms it has `iterations_per_term` × (terms + 1) iterations, and beyond them fewer: the
    stage's cost stops growing with the terms. The vectors are counted here, not by scipy (since scipy 1.16 its
    `max_nfev` leaves the Jacobian's evaluations out); a stage stops before it would pass its budget and keeps the
    coefficients with the smallest gap it rolled out.
    A residual fit matches the equations sample by sample; this matches their solutions, so the phase after many
    periods. Two stages: multiple shooting (windows of :data:`SHOOTING_WINDOW` samples, each rolled out from its
    own encoded start: short rollouts stay near the codes and their gap is smooth in the coefficients), then single
    shooting over the whole training window from the better of the start and that. The coefficients kept are those
    (start, after either stage) with the smallest whole-window gap. A rollout that diverges or leaves the training
    codes by more than :data:`SHOOTING_GUARD_MARGIN` of their span counts as a gap of 10 spreads per sample from
    there on (that trajectory only: one that runs off leaves the others' gaps to guide the search); on a table,
    trials read its continuation beyond its box (:meth:`lnf.tabulated.TabulatedDynamics.continued_off_box`), not
    exact jets.
    Returns the whole-window RMS gap (start, end)."""
    closure = model.closure
    # the closed dynamics (the model's table where it has one), reading the coefficients as they change:
    # model.dynamics() leaves a zero closure out
    base = model.dynamics()
    dynamics = ClosedDynamics(base.base if isinstance(base, ClosedDynamics) else base, closure)
    table = getattr(dynamics.base, "table", None)  # TabulatedDynamics: its Chebyshev table
    cheap = getattr(dynamics, "small_tensors", False) and (table is None or table.coef.numel() <= SHOOTING_TABLE_WORK)
    count = SHOOTING_TRAJECTORIES if cheap else SHOOTING_TRAJECTORIES_EXACT
    rows = np.unique(np.linspace(0, codes.shape[0] - 1, min(count, codes.shape[0])).round().astype(int))
    q, v = model.as_model(codes[rows]), model.as_model(velocities[rows])
    forces = None if controls is None else controls[rows]
    spread = float(q.std().clamp_min(1e-12))
    with torch.no_grad():  # the coefficients in units of the pulled-back potential's range on these codes: the
        # finite-difference steps of the search (10⁻³ of it) then move the rollouts well above float32 round-off
        potential = dynamics.base.potential_energy(q.reshape(-1, q.shape[-1]))
    unit = float((potential.max() - potential.min()).clamp_min(1e-30))
    steps = q.shape[1] - 1
    window = min(SHOOTING_WINDOW, steps)

    # without non-conservative forces the reduced equations do not depend on t: every window is a row of one rollout
    autonomous = bool(getattr(getattr(model, "scene", None), "is_conservative", False))

    def gaps(thetas: np.ndarray, starts: "range | tuple[int, ...]", length: int) -> np.ndarray:
        """The gaps (K, M) of K coefficient vectors `thetas` (K, P), all in one batched rollout per group of windows:
        block k of its rows runs under θ_k (ClosedDynamics.set_row_coefficients)."""
        coef = torch.as_tensor(thetas * unit, dtype=closure.coef.dtype)
        groups = [tuple(starts)] if autonomous else [(s,) for s in starts]  # a forced scene's loads depend on t
        out = []
        try:
            for group in groups:
                first = torch.cat([q[:, s] for s in group]), torch.cat([v[:, s] for s in group])
                rows = len(first[0])
                if forces is not None:  # the loads first: the coefficients ride behind them in `controls`
                    dynamics.controls = forces.repeat(len(group) * len(coef), 1).to(q)
                dynamics.set_row_coefficients(coef.repeat_interleave(rows, 0))
                traj = model.rollout(first[0].repeat(len(coef), 1), first[1].repeat(len(coef), 1), dt=dt,
                                     steps=length, integrator=integrator, t0=t0 + group[0] * dt,
                                     on_divergence="mark", dynamics=dynamics)
                target = torch.cat([q[:, s:s + length + 1] for s in group])
                diff = (traj.q.reshape(len(coef), *target.shape) - target) / spread
                out.append(diff.double().cpu().numpy().reshape(len(coef), -1))
        finally:
            dynamics.set_row_coefficients(None)
        return np.nan_to_num(np.concatenate(out, 1), nan=10.0, posinf=10.0, neginf=-10.0)

    def whole(theta: np.ndarray) -> float:
        return float(np.sqrt(np.mean(gaps(theta[None], (0,), steps) ** 2)))

    def search(theta: np.ndarray, starts: "range | tuple[int, ...]", length: int, stage: str) -> np.ndarray:
        n = len(theta)
        budget = iterations_per_term * (min(n, SHOOTING_BUDGET_TERMS) + 1) ** 2  # vectors, the Jacobians' included
        spent, best, size = 0, (math.inf, theta), 1
        history: list[float] = []  # the best cost before each Jacobian
        began = logged = time.perf_counter()

        def spend(count: int, points: np.ndarray) -> np.ndarray:
            nonlocal spent, best, size, logged
            if spent + count > budget:
                raise _BudgetSpent
            spent += count
            residuals = gaps(points, starts, length)
            costs = (residuals ** 2).sum(1)
            size = residuals.shape[1]
            if costs.min() < best[0]:
                best = (float(costs.min()), points[int(costs.argmin())].copy())
            if time.perf_counter() - logged > SHOOTING_LOG_SECONDS:
                logged = time.perf_counter()
                log.info("closure shooting, %s: %d of %d coefficient vectors rolled out, gap %.3g spreads so far, "
                         "%.0f s", stage, spent, budget, math.sqrt(best[0] / size), logged - began)
            return residuals

        def jacobian(x: np.ndarray) -> np.ndarray:
            # forward differences (scipy's 2-point rule, step 10⁻³ · max(1, |θ_k|)), the n columns and their base
            # point in one batched rollout: n + 1 rollouts of the budget
            history.append(best[0])
            if len(history) > SHOOTING_STALL_ITERATIONS and \
                    history[-1] > (1.0 - SHOOTING_STALL) ** 2 * history[-1 - SHOOTING_STALL_ITERATIONS]:  # costs: gaps²
                raise _Stalled
            h = 1e-3 * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
            r = spend(n + 1, np.vstack([x, x + np.diag(h)]))
            return ((r[1:] - r[0]) / h[:, None]).T

        end = "its budget spent"
        try:
            end = least_squares(lambda x: spend(1, x[None])[0], theta, jac=jacobian, method="lm", x_scale="jac",
                                max_nfev=budget).message
        except _BudgetSpent:
            pass
        except _Stalled:
            end = (f"stalled: the gap shrank by less than {SHOOTING_STALL:.0%} over {SHOOTING_STALL_ITERATIONS} "
                   "iterations")
        log.info("closure shooting, %s: gap %.3g spreads, %d of %d coefficient vectors rolled out, %.0f s (%s)", stage,
                 math.sqrt(best[0] / size), spent, budget, time.perf_counter() - began, end)
        return best[1]  # the search's own end is one of the points it rolled out

    theta0 = closure.coef.detach().double().cpu().numpy() / unit
    # A trial trajectory that runs away from the training codes ends there: past the guard the closure's force is
    # NaN, the row diverges and its gap is 10 spreads from then on, so the search never pays for rollouts that crawl
    # off the codes (stiff implicit solves of the exact pullback). Only that row ends: when one row ended the whole
    # trial, every trial of the soft body's d = 2 search had the same gap and it never moved. On a table, trials past
    # its box read the table's continuation, not exact jets (a search sat 80 min there on the soft body at d = 2);
    # ending them at the box instead stalled the soft body's d = 1 search (0.133 → 0.126 in place of 0.0486 → 0.0144).
    # Single shooting alone stalled where the start's rollouts already ran off (soft body, d = 2: 4.17 → 4.17
    # spreads): every row's gap was the flat 10 of a dead trajectory; short windows keep them alive.
    continuation = getattr(dynamics.base, "continued_off_box", contextlib.nullcontext)
    closure.set_guard(SHOOTING_GUARD_MARGIN, getattr(model, "code_span_floor", 0.0))  # a barely moving POD code may drift
    try:
        with continuation():
            candidates = [(whole(theta0), theta0)]
            starts = tuple(sorted({*range(0, steps - window + 1, window), steps - window}))  # the last ends at T
            if window < steps:
                windowed = search(theta0, starts, window, f"windows of {window} samples")
                candidates.append((whole(windowed), windowed))
            else:  # one window is the whole training window: single shooting alone
                candidates.append(candidates[0])
            # the whole window from the better of the two: where the windows found nothing better, single shooting
            # from the start as before them
            single = search(min(candidates, key=lambda c: c[0])[1], (0,), steps, "the whole window")
            candidates.append((whole(single), single))
    finally:
        closure.set_guard(None)
    log.info("closure shooting: whole-window gap %.3g at the start, %.3g after windows of %d samples, %.3g after the "
             "whole window", candidates[0][0], candidates[1][0], window, candidates[2][0])
    end, best = min(candidates, key=lambda c: c[0])  # ties keep the earlier: the start where nothing was better
    closure.coef.copy_(torch.as_tensor(best * unit, dtype=closure.coef.dtype))
    return candidates[0][0], end
