"""Fitting a model's potential closure ΔṼ after training (lnf/closure.py): the residual of the pulled-back equations
along the encoded training trajectories, one ridge fit per candidate regularizer, and the choice among them (or
none) by validation rollouts. Used by lnf.train, lnf.evaluate [closure_degree=p] and the studies."""
from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Any

import torch

from lnf.baselines.latent_mlp import latent_trajectories
from lnf.closure import ClosureLeftItsRange, equation_residual
from lnf.evaluation_pipeline import EvaluationData, evaluate_model
from lnf.tabulated import TABLE_MARGIN

log = logging.getLogger("lnf.closure")


#: the closure's candidate regularizers (ridge λ, relative to the normal matrix's mean diagonal)
CLOSURE_REGULARIZERS = (1e-8, 1e-5, 1e-2)
CLOSURE_VAL_TRAJECTORIES = 8


def fit_closure(model: Any, datamodule: Any, spec: Any) -> dict[str, float]:
    """Fit the model's potential closure ΔṼ (lnf/closure.py) after training: the pulled-back equations' residual
    along the encoded training trajectories, a ridge fit per regularizer of :data:`CLOSURE_REGULARIZERS`, and the
    one (or none: the pure pullback) whose rollouts of the first validation trajectories have the smallest field
    error within the training horizon. `spec`: the test's EvaluationSpec (its integrator and decoding)."""
    start = time.perf_counter()
    closure = model.closure
    points, values, velocities = (torch.as_tensor(a) for a in datamodule.observations("train"))
    model.eval()
    train, val = datamodule.split("train"), datamodule.split("val")
    controls = None if train.controls is None else torch.as_tensor(train.controls)
    with torch.no_grad():
        q, v = latent_trajectories(model, points, values, velocities)
        codes, residual = equation_residual(model.lagrangian_dynamics(), q, v, datamodule.dt,
                                            float(train.times[0]), controls)
    data = EvaluationData.of_split(val, model.scene, CLOSURE_VAL_TRAJECTORIES)
    check = dataclasses.replace(spec, split="val", label="closure choice: validation rollout", long_steps=0,
                                figures=0, keep_fields=0, progress=False)

    def val_error() -> float:
        try:
            with torch.no_grad():
                err = evaluate_model(model, data, check).metrics["field_rel_l2/in_horizon/median"]
        except ClosureLeftItsRange as exc:  # extrapolating: rejected, and no rollout crawls off the table's box
            log.info("closure candidate rejected: a validation rollout %s", str(exc).replace("codes ", "", 1))
            return math.inf
        return err if math.isfinite(err) else math.inf

    closure.reset()
    best = (val_error(), 0.0, 0.0)  # (error, λ, misfit); λ = 0: none
    chosen = None  # the coefficients of the best candidate, once one beats the pure pullback
    pullback_error = best[0]
    # a candidate whose validation rollout leaves the training codes' range by more than the table's margin is rejected:
    # its polynomial extrapolates there, and a tabulated pullback would fall back to the exact jets
    closure.guard_margin = float((getattr(model, "tabulation", None) or {}).get("margin", TABLE_MARGIN))
    try:
        for lam in CLOSURE_REGULARIZERS:
            misfit = closure.fit(codes, residual, lam)
            err = val_error()
            log.info("closure λ = %.0e: misfit %.3f of the residual, validation field error %.4g in the horizon",
                     lam, misfit, err)
            if err < best[0]:
                best, chosen = (err, lam, misfit), closure.coef.clone()
    finally:  # the fitted model rolls out anywhere
        closure.guard_margin = None
    closure.reset()
    if chosen is not None:  # every fit has the same centre and scale (the codes'): the chosen one's coefficients suffice
        closure.coef.copy_(chosen)
    seconds = time.perf_counter() - start
    log.info("potential closure: %s (validation field error %.4g in the horizon, the pure pullback's %.4g), %.1f s",
             f"λ = {best[1]:.0e}, {len(closure.coef)} terms" if best[1] > 0 else "none (the pure pullback is best)",
             best[0], pullback_error, seconds)
    return {"closure_regularizer": best[1], "closure_val_error": best[0], "closure_pullback_val_error": pullback_error,
            "closure_misfit": best[2], "closure_seconds": seconds}
