"""model.w0=auto: the candidates from the body's size, the search, and a run that chooses and stores its w0."""
import contextlib
import json
import math
from pathlib import Path

import pytest
import torch

from helpers import METRICS_ONLY, TINY, compose_config
from lnf.w0_search import SPANS, search_w0, w0_for_span


def test_candidates_scale_with_the_body_and_its_dimension():
    assert w0_for_span([[-1, 1], [-1, 1]], 10.0) == pytest.approx(10.0)  # the pendulum's hand-chosen w0
    assert w0_for_span([[0, 1], [0, 0.4]], 5.0) == pytest.approx(10.0)  # the cantilever's
    assert w0_for_span([[0, 0.5], [0, 0.15], [0, 0.1]], 5.0) == pytest.approx(30.0)  # the soft body's
    assert w0_for_span([[0, 1000.0], [0, 400.0]], 5.0) == pytest.approx(0.01)  # the cantilever in millimetres
    with pytest.raises(ValueError, match="bounds"):
        w0_for_span([[0, 0], [0, 0]], 5.0)


class _Quadratic(torch.nn.Module):
    """A stand-in model whose loss is finite except at w0 = 3, scored by its distance from w0 = 7."""

    def __init__(self, w0: float) -> None:
        super().__init__()
        self.w0, self.x = w0, torch.nn.Parameter(torch.zeros(1))

    def losses(self, *args, **kwargs):
        loss = (self.x - 1).pow(2).sum() * (math.inf if self.w0 == 3 else 1)
        return {"loss": loss}


class _Batch:
    points = values = velocities = potential = gradients = None


def test_the_search_keeps_the_best_score_and_leaves_out_a_diverging_candidate():
    outcome = search_w0(_Quadratic, [3.0, 5.0, 8.0, 20.0], lambda: [_Batch()], lambda m: abs(m.w0 - 7), steps=5)
    assert outcome.chosen == 8.0 and outcome.scores[3.0] == math.inf and "<- chosen" in outcome.table()
    with pytest.raises(RuntimeError, match="every candidate w0"):
        search_w0(_Quadratic, [3.0], lambda: [_Batch()], lambda m: 0.0, steps=5)


def test_the_search_counts_every_candidates_steps_on_one_progress_bar(monkeypatch):
    from lnf import w0_search

    seen = []

    @contextlib.contextmanager
    def recording(enabled, total, description, unit="frames"):
        seen.append((enabled, total, description, unit))
        done = []
        yield done.append
        seen.append(sum(done))

    monkeypatch.setattr(w0_search, "progress_bar", recording)
    search_w0(_Quadratic, [3.0, 5.0, 8.0], lambda: [_Batch()], lambda m: abs(m.w0 - 7), steps=5, progress=True)
    assert seen == [(True, 15, "model.w0=auto", "steps"), 15]  # the diverging w0 = 3 counts its skipped steps


def test_near_ties_go_to_the_smaller_w0():
    errors = {5.0: 0.7458, 10.0: 0.7039, 20.0: 0.7003, 40.0: 0.7232}  # the cantilever after 100 steps
    outcome = search_w0(_Quadratic, list(errors), lambda: [_Batch()], lambda m: errors[m.w0], steps=1)
    assert outcome.chosen == 10.0  # 0.5 % behind 20: tied; 5 is 6.5 % behind: not
    errors = {5.0: 1.004, 10.0: 0.1657, 20.0: 0.0833}  # the pendulum: 20 halves 10's error
    assert search_w0(_Quadratic, list(errors), lambda: [_Batch()], lambda m: errors[m.w0], steps=1).chosen == 20.0


@pytest.mark.slow
def test_a_run_with_w0_auto_chooses_a_candidate_and_stores_it(tmp_path):
    from lnf import load
    from lnf.train import train

    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "trainer.max_epochs=1", "logger=csv",
                                   "model.w0=auto", *TINY,
                                   # checks only the chosen w0: no figures, validation rollouts or long-horizon check
                                   *METRICS_ONLY],
                         tmp_path)
    metrics = train(cfg)
    candidates = [w0_for_span([[-1, 1], [-1, 1]], s) for s in SPANS]
    assert metrics["w0"] in candidates
    assert json.loads((Path(cfg.paths.output_dir) / "metrics.json").read_text())["w0"] == metrics["w0"]
    model = load(Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt")
    assert model.field.w0 == pytest.approx(metrics["w0"])  # the checkpoint rebuilds the chosen w0, not "auto"


def test_a_word_other_than_auto_is_refused_naming_the_key(tmp_path):
    from lnf.train import train

    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "model.w0=fast", *TINY], tmp_path)
    with pytest.raises(Exception, match=r"model\.w0 must be .* or auto"):
        train(cfg)


@pytest.mark.slow
def test_the_search_shares_one_pod_fit_with_its_candidates_and_the_run(tmp_path, caplog):
    """model.pod_subspace=true with w0=auto: the POD part is fitted once, and every candidate and the trained model
    start from it."""
    import logging

    from lnf import load
    from lnf.train import train

    cfg = compose_config("train", ["+experiment=pendulum", "trainer=smoke", "trainer.max_epochs=1", "logger=csv",
                                   "model.w0=auto", "model.pod_subspace=true", "model.pod_degree=4",
                                   *TINY,
                                   # checks only the POD fit: no figures, validation rollouts or long-horizon check
                                   *METRICS_ONLY],
                         tmp_path)
    with caplog.at_level(logging.INFO, logger="lnf.pod"):
        metrics = train(cfg)
    assert caplog.text.count("modes capture") == 1 and "pod_energy_captured" in metrics
    model = load(Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt")
    assert bool(model.field.fitted) and float(model.field.linear.modes.abs().max()) > 0
