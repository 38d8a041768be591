"""Choosing the SIREN frequency w0 from the body and the data (``model.w0: auto``): a short guided search.

The first sine layer of :class:`lnf.siren.ModulatedSiren` starts with frequencies up to w0 / dim_B per unit length,
so the phase its fastest wave spans across a body of longest side L is w0 L / dim_B: the same w0 is a smooth field
on a small body and noise on a large one (or in other units). The measured choices of lnf's scenes span 5 rad (the
cantilever, w0 = 10 on 1 m, and the soft body, w0 = 30 on 0.5 m in 3-D) to 10 rad (the pendulum image, w0 = 10 on
2 m), and a field is lost at a few times off: the cantilever at w0 = 3 (1.5 rad) had 10x its error at 10, the soft
body at 10 (1.7 rad) 0.25 in the horizon.

:func:`search_w0` trains one model per candidate span (:data:`SPANS`) for the same few steps from the same seed,
and keeps the smallest w0 whose projection error on the validation trajectories' fine points is within 2 % of the
lowest (:data:`TIE`; after 100 steps the cantilever's 10 and 20 differed by 0.5 %, the pendulum's by 2x). Plain
torch; ``lnf.train`` runs it before training when ``model.w0`` is ``auto``, and the checkpoint stores the number.
"""
from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import numpy as np
import torch

from lnf import metrics as M
from lnf.progress import progress_bar

log = logging.getLogger(__name__)

#: phases (rad) the first layer's fastest initial wave spans over the body's longest side: the candidates
SPANS = (2.5, 5.0, 10.0, 20.0)
#: training steps per candidate: enough to tell a field that fits from one that does not (not to train it)
STEPS = 100
#: candidates whose error is within this fraction of the best count as tied: the smallest w0 of them is chosen
TIE = 0.02


def w0_for_span(bounds: Sequence[Sequence[float]], span: float) -> float:
    """w0 whose fastest initial first-layer wave spans `span` radians over the body's longest side:
    w0 = span · dim_B / L, `bounds` [[lo, hi], ...] (one pair per body axis, in the scene's length unit)."""
    extent = max(float(hi) - float(lo) for lo, hi in bounds)
    if not (math.isfinite(extent) and extent > 0):
        raise ValueError(f"model.w0=auto needs a body of positive finite size; the scene's bounds are {bounds!r}")
    return float(span) * len(bounds) / extent


@dataclass
class W0Search:
    """The outcome: `chosen` w0, and each candidate's projection error on the validation split (inf: it diverged)."""

    chosen: float
    scores: dict[float, float]

    def table(self) -> str:
        return "\n".join(f"  w0 = {w0:<8.4g} validation projection error {score:.4g}"
                         + ("   <- chosen" if w0 == self.chosen else "") for w0, score in self.scores.items())


def projection_error(model: torch.nn.Module, split, train_times: int, snapshots: int = 64) -> float:
    """Median relative L² error of the validation fields projected through the model, on the split's fine points:
    q̃ = ρ̃(the masked coarse observations), φ(q̃) decoded on the fine points, against the true fields (`snapshots`
    spread over the trajectories and the first `train_times` samples). Unlike the training losses, it sees the
    fields between the coarse points, where a w0 too high for the grid aliases."""
    n = len(split)
    per = max(1, -(-snapshots // n))
    times = np.unique(np.linspace(0, train_times - 1, per).round().astype(int))
    fine = torch.as_tensor(split.fine_points)
    uniform = np.ones(len(fine))
    errors = []
    with torch.no_grad():
        for i in range(n):
            observed = torch.as_tensor(split.coarse_points[split.masks[i]])
            values = torch.as_tensor(split.coarse_fields[i, times][:, split.masks[i]])
            codes = model.reduce(observed, values)
            pred = model.decode(codes, fine, outside="ignore").double().numpy()[:, None]  # each snapshot on its own
            true = np.asarray(split.fields[i, times], dtype=np.float64)[:, None]
            errors.append(M.field_rel_l2(pred, true, uniform, np.ones(1, bool)))
    return float(torch.from_numpy(np.concatenate(errors)).median())  # of an even count, the lower middle one


def _cycled(batches: Callable[[], Iterable]) -> Iterable:
    while True:
        yield from batches()


def _candidate_score(build: Callable[[float], torch.nn.Module], w0: float, train_batches: Callable[[], Iterable],
                     score: Callable[[torch.nn.Module], float], steps: int, lr: float, seed: int,
                     advance: Callable[[int], None]) -> float:
    """`score` of `build(w0)` after `steps` Adam steps; inf for a candidate whose loss blows up."""
    torch.manual_seed(seed)
    model = build(w0)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    done = 0
    try:
        for batch in itertools.islice(_cycled(train_batches), steps):
            loss = model.losses(batch.points, batch.values, batch.velocities, batch.potential,
                                gradients=batch.gradients)["loss"]
            if not torch.isfinite(loss):
                raise FloatingPointError(f"loss {loss.item()}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            done += 1
            advance(1)
        value = score(model)
    except FloatingPointError as err:  # a candidate that blows up is not chosen
        log.info("model.w0=auto: w0 = %.4g left out (%s)", w0, err)
        advance(steps - done)
        return math.inf
    return value if math.isfinite(value) else math.inf


def search_w0(build: Callable[[float], torch.nn.Module], candidates: Sequence[float],
              train_batches: Callable[[], Iterable], score: Callable[[torch.nn.Module], float],
              steps: int = STEPS, lr: float = 3e-4, seed: int = 0, progress: bool = False) -> W0Search:
    """Train `build(w0)` for `steps` Adam steps (learning rate `lr`, from seed `seed`) on `train_batches()` (cycled
    :class:`lnf.training.batch.SnapshotBatch` es) for each w0 of `candidates`; the smallest w0 whose `score(model)`
    is within :data:`TIE` of the lowest wins. `progress`: a progress bar over all the candidates' steps."""
    if not candidates:
        raise ValueError("search_w0: no candidate w0")
    scores: dict[float, float] = {}
    with progress_bar(progress, steps * len(candidates), "model.w0=auto", "steps") as advance:
        for w0 in candidates:
            scores[float(w0)] = _candidate_score(build, float(w0), train_batches, score, steps, lr, seed, advance)
            log.info("model.w0=auto: w0 = %.4g scored %.4g", w0, scores[float(w0)])
    finite = {w0: v for w0, v in scores.items() if math.isfinite(v)}
    if not finite:
        raise RuntimeError("model.w0=auto: every candidate w0 (" + ", ".join(f"{w:.4g}" for w in candidates)
                           + ") gave a non-finite loss; set model.w0 to a number, or lower optimizer.lr")
    best = min(finite.values())
    # the smallest w0 within TIE of the best: a faster first layer must earn its place (it fits the observed points
    # sooner, and may alias between them later)
    return W0Search(chosen=min(w0 for w0, v in finite.items() if v <= (1 + TIE) * best), scores=scores)


def choose_w0(build: Callable[[float], torch.nn.Module], bounds: Sequence[Sequence[float]], datamodule,
              lr: float, seed: int = 0, spans: Sequence[float] = SPANS, steps: int = STEPS,
              progress: bool = False) -> W0Search:
    """:func:`search_w0` over the w0 of `spans` on this body (`bounds`): trained on a data module's training batches
    (``train_dataloader()``), scored by :func:`projection_error` on its validation split (``split("val")``,
    ``train_times``); the outcome is logged as a table."""
    candidates = [w0_for_span(bounds, span) for span in spans]
    log.info("model.w0=auto: %d steps for each of w0 = %s (phase spans %s rad over the body's longest side)",
             steps, ", ".join(f"{w:.4g}" for w in candidates), ", ".join(f"{s:g}" for s in spans))
    val = datamodule.split("val")
    outcome = search_w0(build, candidates, datamodule.train_dataloader,
                        lambda model: projection_error(model, val, datamodule.train_times), steps=steps, lr=lr,
                        seed=seed, progress=progress)
    log.info("model.w0=auto chose w0 = %.4g (stored in the checkpoint; model.w0=%.4g repeats it):\n%s",
             outcome.chosen, outcome.chosen, outcome.table())
    return outcome
