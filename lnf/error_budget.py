"""Reading a run's test error against the embedding's own floor: where the accuracy is lost.

The projection error ``projection_rel_l2`` is the floor: the error of the true fields projected onto the embedding
(q̃ = ρ̃(fields), decoded again), with no dynamics. A rollout can do no better. So the test error splits in two:

- the **floor** itself, the embedding's share: high when φ cannot represent the states (near 1: it collapsed, often
  a SIREN frequency w0 far from the body's size and the field's wavelengths, or too short a training);
- the **ratio** ``field_rel_l2 / projection_rel_l2``, the dynamics' share: high when the embedding holds the states
  but the reduced equations pulled back through it (M̃, Ṽ and their derivatives) do not follow the data.

:func:`read_error_budget` turns a metrics dict into these findings, in words; ``lnf.train`` and ``lnf.evaluate``
log them after the test evaluation. Plain Python; no torch.
"""
from __future__ import annotations

import math
from typing import Mapping

#: a floor above this is a collapsed embedding; a rollout error above RATIO × the floor is lost in the dynamics
COLLAPSED = 0.5
RATIO = 3.0


def read_error_budget(metrics: Mapping[str, float], window: str = "all") -> list[str]:
    """Findings (sentences) on `metrics` (a metrics.json dict) in one time window ("all", "in_horizon",
    "extrapolation"); empty when the floor or the error is missing or not finite, or nothing stands out."""
    floor = metrics.get(f"projection_rel_l2/{window}/median")
    error = metrics.get(f"field_rel_l2/{window}/median")
    if floor is None or error is None or not math.isfinite(float(floor)):
        return []
    floor, error = float(floor), float(error)
    out = []
    if floor >= COLLAPSED:
        out.append(f"the embedding collapsed: its projection floor projection_rel_l2/{window}/median = {floor:.3g} "
                   "(near 1: φ does not represent the fields even without dynamics). Try another model.w0 (the "
                   "SIREN's first-layer frequency against the body's size: lower for smooth fields on a large body), "
                   "more epochs, or check that the data's fields vary between trajectories")
    elif not math.isfinite(error):
        out.append(f"the rollout diverged (field_rel_l2/{window}/median = {error}) while the projection floor is "
                   f"{floor:.3g}: the embedding holds the states, the pulled-back dynamics do not (see the divergence "
                   "warning for its cause)")
    elif floor > 0 and error > RATIO * floor:
        out.append(f"the dynamics lose the accuracy: field_rel_l2/{window}/median = {error:.3g} is "
                   f"{error / floor:.3g}× the projection floor {floor:.3g}. The embedding holds the states, but the "
                   "equations pulled back through it do not follow them (its tangent and curvature, which define M̃ "
                   "and Ṽ, are not trained to be right): try the integrator's order 4, a larger latent dimension, or "
                   "compare with a baseline (experiments/operator_inference.py)")
    return out
