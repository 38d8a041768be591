"""Evaluation in bounded memory: evaluate_rollouts decodes and compares the frames a block at a time, and its
metrics equal those of the unchunked evaluation (all fields at once, lnf.metrics on the full arrays) it replaced."""
from __future__ import annotations

import contextlib
import numpy as np
import pytest
import torch

from lnf import metrics as M
from lnf.evaluation import evaluate_rollouts, reduction_subset, trajectory_controls
from lnf.evaluation_cost import chunked_energy, evaluation_cost, frame_block
from helpers import DivergesAtStep
from lnf.integrators import get_integrator
from lnf.model import build_model
from lnf.quadrature import midpoint_grid

SCENE = {"_target_": "lnf.scenes.LiftedPendulum"}
TIMING = ("seconds",)


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return build_model(SCENE, {"latent_dim": 1, "width": 16, "depth": 2, "hyper_width": 8, "hyper_depth": 1},
                       {"_target_": "lnf.quadrature.GaussLegendre", "order": 4}).eval()


@pytest.fixture(scope="module")
def case(model):
    scene = model.scene
    times = 0.05 * np.arange(14)
    states = scene.simulate(np.array([[0.5, 0.0], [1.0, 0.2], [-0.7, 0.4]]), times)
    points = midpoint_grid(10, scene.bounds).numpy()
    fields, velocities = scene.fields(states, points)
    return states, times, points, fields.astype(np.float32), velocities.astype(np.float32)


@torch.no_grad()
def unchunked_reference(model, states, times, points, train_horizon, true_fields, true_velocities, grid_shape,
                        max_reduction_points, snapshot_chunk=32, integrator="implicit_midpoint"):
    """The evaluation as it was before it was chunked: every frame decoded at once, the float64 fields of all
    trajectories in memory, lnf.metrics on the full (n, T, N, A) arrays, one energy batch."""
    scene, p = model.scene, model.reference_tensor()
    n, T = states.shape[:2]
    dt = float(times[1] - times[0])
    chunked = lambda fn, x: torch.cat([fn(x[i:i + snapshot_chunk]) for i in range(0, x.shape[0], snapshot_chunk)])
    pts = torch.as_tensor(points, dtype=p.dtype)
    sub = reduction_subset(len(points), grid_shape, max_reduction_points)
    pts_r = pts[torch.as_tensor(sub)]
    fields_r = torch.as_tensor(np.asarray(true_fields)[:, :, sub], dtype=p.dtype)
    vel0 = torch.as_tensor(np.asarray(true_velocities)[:, 0, sub], dtype=p.dtype)
    q0 = model.reduce(pts_r, fields_r[:, 0])
    v0 = model.project_velocity(q0, pts_r, vel0)
    dynamics = model.dynamics(None)
    traj = model.rollout(q0, v0, dt=dt, steps=T - 1, integrator=get_integrator(integrator),
                         on_divergence="mark", controls=trajectory_controls(scene, states[:, 0], q0), dynamics=dynamics)
    d = model.latent_dim
    flat_q = traj.q.reshape(n * T, d)
    finite = torch.isfinite(flat_q).all(-1)
    pred = chunked(lambda c: model.decode(c, pts), torch.where(finite[:, None], flat_q, torch.zeros_like(flat_q)))
    pred = torch.where(finite[:, None, None], pred, float("nan")).reshape(n, T, *pred.shape[1:])
    q_ref = chunked(lambda f: model.reduce(pts_r, f), fields_r.reshape(n * T, *fields_r.shape[2:]))
    proj = chunked(lambda c: model.decode(c, pts), q_ref).reshape(n, T, *pred.shape[2:])
    kin, pot = model.energy(torch.where(finite[:, None], flat_q, 0.0),
                            torch.where(finite[:, None], traj.v.reshape(n * T, d), 0.0))
    kin, pot = torch.where(finite, kin, float("nan")), torch.where(finite, pot, float("nan"))
    kin, pot = (e.reshape(n, T).double().numpy() for e in (kin, pot))
    kin_true, pot_true = scene.true_energy_parts(states)
    weights = np.full(len(points), 1.0 / len(points))
    pred_np, true_np = pred.double().numpy(), np.asarray(true_fields, dtype=np.float64)
    out = {**M.field_metrics("field_rel_l2", pred_np, true_np, weights, times, train_horizon),
           **M.field_metrics("projection_rel_l2", proj.double().numpy(), true_np, weights, times, train_horizon),
           **M.latent_rmse(traj.q.double().numpy(), q_ref.reshape(n, T, d).double().numpy()),
           **M.energy_metrics(kin + pot, kin_true + pot_true, scene.energy_scale)}
    vpt = M.valid_prediction_time(pred_np, true_np, weights, times)
    out.update({"vpt/median": float(np.median(vpt)), "vpt/min": float(np.min(vpt))})
    return out, pred_np, true_np


def _results(metrics):
    return {k: v for k, v in metrics.items() if not any(t in k for t in TIMING)}


def test_chunked_evaluation_equals_the_unchunked_reference(model, case):
    states, times, points, fields, velocities = case
    reference, pred_all, true_all = unchunked_reference(model, states, times, points, 0.35, fields, velocities,
                                                        (10, 10), 25)
    kw = dict(true_fields=fields, true_velocities=velocities, grid_shape=(10, 10), max_reduction_points=25,
              decoding="exact")  # the reference decodes exactly, to 1e-6
    whole = evaluate_rollouts(model, states, times, points, 0.35, **kw)
    # blocks of 4 frames (2 decoding batches of 2), across trajectory boundaries (14 frames each); one trajectory kept
    block_bytes = 4 * len(points) * 8
    assert frame_block(len(points), 1, 2, block_bytes) == 4
    chunked = evaluate_rollouts(model, states, times, points, 0.35, snapshot_chunk=2, block_bytes=block_bytes,
                                keep_fields=1, **kw)
    for key, value in reference.items():
        assert whole.metrics[key] == pytest.approx(value, rel=1e-6, abs=1e-12), key
        assert chunked.metrics[key] == pytest.approx(value, rel=1e-6, abs=1e-12), key
    assert _results(chunked.metrics).keys() == _results(whole.metrics).keys()
    assert whole.pred_fields.shape == pred_all.shape and np.array_equal(whole.true_fields, true_all)
    np.testing.assert_allclose(whole.pred_fields, pred_all, rtol=1e-6, atol=1e-7)
    assert chunked.pred_fields.shape == (1, *pred_all.shape[1:])  # only the kept trajectory's fields
    np.testing.assert_allclose(chunked.pred_fields[0], pred_all[0], rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(chunked.true_fields[0], true_all[0])
    np.testing.assert_allclose(chunked.q_ref, whole.q_ref, rtol=1e-6, atol=1e-7)


def test_a_diverged_trajectory_gives_the_same_metrics_chunked(model, case):
    """Frames after a divergence are NaN, and are not decoded: the metrics are those of the reference still."""
    states, times, points, fields, velocities = case
    reference, pred_all, _ = unchunked_reference(model, states, times, points, 0.35, fields, velocities, (10, 10), 25,
                                                 integrator=DivergesAtStep(5))
    chunked = evaluate_rollouts(model, states, times, points, 0.35, true_fields=fields, true_velocities=velocities,
                                grid_shape=(10, 10), max_reduction_points=25, integrator=DivergesAtStep(5),
                                snapshot_chunk=2, block_bytes=4 * len(points) * 8, keep_fields=2)
    assert chunked.metrics["diverged_count"] == 1.0
    for key, value in reference.items():
        assert chunked.metrics[key] == pytest.approx(value, rel=1e-6, abs=1e-12, nan_ok=True), key
    assert np.isnan(chunked.pred_fields[1, 5:]).all() and np.isfinite(chunked.pred_fields[1, :5]).all()
    np.testing.assert_allclose(chunked.pred_fields, pred_all[:2], rtol=1e-6, atol=1e-7)


def test_fields_from_the_scene_block_by_block_equal_the_stored_ones(model, case):
    """Without stored fields the scene computes them a block at a time (and the velocities only at t0)."""
    states, times, points, fields, velocities = case
    rng = np.random.default_rng(0)
    scattered = rng.uniform(-1, 1, size=(70, 2)).astype(np.float32)
    f64, v64 = model.scene.fields(states, scattered)
    stored = evaluate_rollouts(model, states, times, scattered, 0.35, true_fields=f64, true_velocities=v64,
                               max_reduction_points=20)
    computed = evaluate_rollouts(model, states, times, scattered, 0.35, max_reduction_points=20, snapshot_chunk=4,
                                 block_bytes=8 * 70 * 8, keep_fields=0, progress=True)
    for key, value in _results(stored.metrics).items():
        assert computed.metrics[key] == pytest.approx(value, rel=1e-6, abs=1e-12), key
    assert computed.pred_fields.shape == (0, len(times), 70, 1)


def test_energies_in_batches_equal_one_batch(model):
    q, v = torch.randn(50, 1), torch.randn(50, 1)
    kin, pot = model.energy(q, v)
    kin_c, pot_c = chunked_energy(model, q, v, max_state_points=16 * 7)  # 7 states per batch on 4×4 points
    torch.testing.assert_close(kin_c, kin, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(pot_c, pot, rtol=1e-6, atol=1e-7)


def test_the_cost_is_said_in_words():
    cost = evaluation_cost(16, 400, 16384, 1, keep_fields=2, quadrature_points=64)
    text = cost.describe()
    assert "16 trajectories × 400 frames × 16384 points" in text and "400.0 MB in float32" in text
    assert "64 quadrature points" in text and "keeping the fields of 2 trajectories" in text
    assert cost.peak_bytes < cost.unchunked_bytes / 4  # bounded: not all fields at once
    other = evaluation_cost(16, 100, 20000, 1, keep_fields=2, quadrature_points=4096, trained_quadrature_points=64)
    assert "the checkpoint's rule has 64: the rollout costs about 64× as much" in other.describe()


def test_the_cost_counts_integrator_substeps_and_all_it_holds():
    """The cost line used to ignore integrator.substeps; the memory estimate counts states, codes and energies."""
    plain = evaluation_cost(16, 400, 16384, 1, keep_fields=2)
    cost = evaluation_cost(16, 400, 16384, 1, keep_fields=2, substeps=5, state_dim=2, latent_dim=2, body_dim=2,
                           long_trajectories=4, long_steps=1000)
    assert cost.rollout_steps == 399 * 5 and plain.rollout_steps == 399 and cost.long_rollout_steps == 5000
    text = cost.describe()
    assert "the rollout takes 1995 integration steps per trajectory (399 sample intervals × integrator.substeps=5)" \
        in text and "the long-horizon check 5000 steps (1000 × 5) of 4 trajectories" in text, text
    assert cost.memory_bytes > cost.peak_bytes and cost.rollout_memory_bytes > plain.rollout_memory_bytes
    huge = evaluation_cost(16, 2 * 10 ** 10, 10 ** 12, 1)  # sizes only: nothing is allocated
    assert huge.memory_bytes > 2 ** 60 and "GB" in huge.describe()


def test_the_long_horizon_check_counts_its_steps_on_a_progress_bar(model, case, monkeypatch):
    from lnf import evaluation

    states, _, points, _, _ = case
    seen = []

    @contextlib.contextmanager
    def recording(enabled, total, description, unit="frames"):
        seen.append((enabled, total, unit))
        done = []
        yield done.append
        seen.append(sum(done))

    monkeypatch.setattr(evaluation, "progress_bar", recording)
    shown = evaluation.long_horizon_energy(model, states[:, 0], points, 0.05, 30, integrator="rk4", progress=True)
    assert seen == [(True, 30, "steps"), 30]
    quiet = evaluation.long_horizon_energy(model, states[:, 0], points, 0.05, 30, integrator="rk4")
    assert {k: v for k, v in shown.items() if "seconds" not in k} == {k: v for k, v in quiet.items() if "seconds" not in k}
