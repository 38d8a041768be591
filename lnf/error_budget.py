"""Reading a run's test error against the embedding's own floor: where the accuracy is lost.

The projection error ``projection_rel_l2`` is the floor: the error of the true fields projected onto the embedding
(q̃ = ρ̃(fields), decoded again), with no dynamics. A rollout can do no better. So the test error splits in two:

- the **floor** itself, the embedding's share: high when φ cannot represent the states (near 1: it collapsed, often
  a SIREN frequency w0 far from the body's size and the field's wavelengths, or too short a training);
- the **ratio** ``field_rel_l2 / projection_rel_l2``, the dynamics' share: high when the embedding holds the states
  but the reduced equations pulled back through it (M̃, Ṽ and their derivatives) do not follow the data.

:func:`read_error_budget` turns a metrics dict into these findings, in words; ``lnf.train`` and ``lnf.evaluate``
log them after the test evaluation, with a word on stiff dynamics (many automatic substeps) and the clamp. Plain
Python; no torch.
"""
from __future__ import annotations

import math
from typing import Mapping, Optional

#: a floor above this is a collapsed embedding; a rollout error above RATIO × the floor is lost in the dynamics
COLLAPSED = 0.5
RATIO = 3.0
#: a rollout that needed this many integration steps per sample (automatic substeps) has stiff dynamics
STIFF_SUBSTEPS = 8
#: what to try on a collapsed embedding, where the model does not say (``ReducedModel.collapse_advice``)
SIREN_COLLAPSE_ADVICE = ("Try another model.w0 (the SIREN's first-layer frequency against the body's size: lower for "
                         "smooth fields on a large body), more epochs, or check that the data's fields vary between "
                         "trajectories")


def stiffness_finding(metrics: Mapping[str, float], clamped: bool = False) -> list[str]:
    """A finding when the test rollout needed ≥ STIFF_SUBSTEPS automatic substeps (``substeps`` in `metrics`): the
    pulled-back dynamics are stiff; with the clamp (`clamped`, φ = s(X) ψ) the likely cause is named."""
    substeps = metrics.get("substeps")
    if substeps is None or not math.isfinite(float(substeps)) or float(substeps) < STIFF_SUBSTEPS:
        return []
    text = (f"the pulled-back dynamics are stiff: the test rollout took {float(substeps):.0f} integration steps per "
            "sample (its fastest reduced frequency that many times what the step resolves), and costs as much")
    if clamped:
        text += (". With model.clamp=true, φ = s(X) ψ: the factor s steepens ∇_X φ next to the clamp, and the "
                 "elastic energy pulled back through it grows stiff; compare a run with model.clamp=false, or keep "
                 "∇_X φ in check with model.gradient_weight > 0 where the scene gives field gradients")
    else:
        text += ("; a latent direction the data barely excite is the usual cause (compare a smaller "
                 "model.latent_dim, or model.mass_condition_weight > 0)")
    return [text]


def read_error_budget(metrics: Mapping[str, float], window: str = "all", clamped: bool = False,
                      closed: bool = False, collapse_advice: Optional[str] = None) -> list[str]:
    """Findings (sentences) on `metrics` (a metrics.json dict) in one time window ("all", "in_horizon",
    "extrapolation"); empty when the floor or the error is missing or not finite, or nothing stands out. `clamped`:
    the model's field is clamped (``model.clamp=true``), named as a likely cause of stiff dynamics; `closed`: its
    dynamics already carry a fitted potential closure (else one is suggested where the dynamics lose the accuracy);
    `collapse_advice`: what the model says to try when its embedding collapsed (None: a SIREN's knobs)."""
    out = stiffness_finding(metrics, clamped)
    floor = metrics.get(f"projection_rel_l2/{window}/median")
    error = metrics.get(f"field_rel_l2/{window}/median")
    if floor is None or error is None or not math.isfinite(float(floor)):
        return out
    floor, error = float(floor), float(error)
    if floor >= COLLAPSED:
        out.append(f"the embedding collapsed: its projection floor projection_rel_l2/{window}/median = {floor:.3g} "
                   "(near 1: φ does not represent the fields even without dynamics). "
                   + (collapse_advice or SIREN_COLLAPSE_ADVICE))
    elif not math.isfinite(error):
        out.append(f"the rollout diverged (field_rel_l2/{window}/median = {error}) while the projection floor is "
                   f"{floor:.3g}: the embedding holds the states, the pulled-back dynamics do not (see the divergence "
                   "warning for its cause)")
    elif floor > 0 and error > RATIO * floor:
        out.append(f"the dynamics lose the accuracy: field_rel_l2/{window}/median = {error:.3g} is "
                   f"{error / floor:.3g}× the projection floor {floor:.3g}. The embedding holds the states, but the "
                   "equations pulled back through it do not follow them (its tangent and curvature, which define M̃ "
                   "and Ṽ, are not trained to be right): try "
                   + ("" if closed else "a potential closure fitted to the observed motion (model.closure_degree=4, "
                      "with integrator.order=4; lnf.evaluate closure_degree=4 on this checkpoint), ")
                   + "the integrator's order 4, a larger latent dimension, or compare with a baseline "
                   "(experiments/operator_inference.py)")
    return out

