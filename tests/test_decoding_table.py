"""Tabulated decoding (lnf/decoding_table.py): a Chebyshev table of φ in the codes on fixed points, its measured
error, its box, and its use by evaluate_rollouts (the same metrics as exact decoding, within its tolerance)."""
from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from lnf.decoding_table import DecodingTable, TabulatedField, code_box
from lnf.evaluation import evaluate_rollouts, frame_decoder
from lnf.model import build_model
from lnf.quadrature import midpoint_grid

POINTS = torch.linspace(-1.0, 1.0, 50, dtype=torch.float64)[:, None]


class Smooth:
    """φ(q, x) = (sin(3 q₀ x + q₁), cos(q₀ + x²)) on POINTS: (B, d) → (B, N, 2); counts the codes it decodes."""

    def __init__(self, d: int):
        self.d, self.calls = d, 0

    def __call__(self, q: torch.Tensor) -> torch.Tensor:
        self.calls += len(q)
        q1 = q[:, 1:2] if self.d > 1 else 0.0
        x = POINTS[:, 0][None]
        return torch.stack([torch.sin(3 * q[:, :1] * x + q1), torch.cos(q[:, :1] + x ** 2)], -1)


@pytest.mark.parametrize("d", [1, 2])
def test_the_table_meets_its_tolerance_at_fresh_codes(d):
    decode = Smooth(d)
    like = torch.zeros((), dtype=torch.float64)
    table = DecodingTable.build(decode, [-1.0] * d, [1.0] * d, like, n_points=50, field_dim=2, tol=1e-9,
                                min_nodes=4, max_nodes=64)
    assert table is not None and table.error <= 1e-9 and table.n > 4  # doubled from 4 nodes
    q = torch.rand(200, d, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 2 - 1
    exact = decode(q)
    err = (table(q) - exact).flatten(1).norm(dim=-1).max() / exact.flatten(1).norm(dim=-1).max()
    assert float(err) <= 1e-8


def test_codes_outside_the_box_are_decoded_exactly():
    decode = Smooth(1)
    like = torch.zeros((), dtype=torch.float64)
    table = DecodingTable.build(decode, [0.0], [0.5], like, n_points=50, field_dim=2, tol=1e-9, min_nodes=8)
    q = torch.tensor([[0.25], [2.0], [-1.0]], dtype=torch.float64)
    before = decode.calls
    out = table(q)
    assert decode.calls - before == 2  # only the two codes outside [0, 0.5]
    torch.testing.assert_close(out[1:], decode(q[1:]))
    torch.testing.assert_close(out[:1], decode(q[:1]), atol=1e-8, rtol=0)


def test_no_table_where_it_cannot_meet_the_tolerance_or_costs_more_than_it_saves(caplog):
    like = torch.zeros((), dtype=torch.float64)
    kink = lambda q: (q.abs() * POINTS[:, 0][None]).unsqueeze(-1)  # |q|: Chebyshev converges slowly
    with caplog.at_level(logging.INFO, logger="lnf.decoding_table"):
        assert DecodingTable.build(kink, [-1.0], [1.0], like, 50, 1, tol=1e-9, min_nodes=4, max_nodes=16) is None
        assert "meets the tolerance" in caplog.text
        assert DecodingTable.build(Smooth(1), [-1.0], [1.0], like, 50, 2, budget=20) is None
        assert "costs more decodings" in caplog.text
        assert DecodingTable.build(Smooth(1), [np.nan], [1.0], like, 50, 2) is None


def test_a_table_with_derivatives_gives_the_jet_that_the_reduction_iterates_on():
    decode = Smooth(1)

    def jacobian(q):  # ∂φ/∂q₀ of Smooth(1): (B, N, 2, 1)
        x = POINTS[:, 0][None]
        return torch.stack([3 * x * torch.cos(3 * q[:, :1] * x), -torch.sin(q[:, :1] + x ** 2)], -1)[..., None]

    like = torch.zeros((), dtype=torch.float64)
    table = DecodingTable.build(decode, [-1.0], [1.0], like, 50, 2, tol=1e-9, min_nodes=8, jacobian=jacobian)
    assert table is not None and table.derivatives and table.error <= 1e-9
    field = TabulatedField(table, POINTS, lambda q: (decode(q), jacobian(q)))
    q = torch.tensor([[0.3], [-0.8], [1.5]], dtype=torch.float64)  # the last outside the box: exact
    jet = field.jet(q, POINTS)
    torch.testing.assert_close(jet.value, decode(q), atol=1e-8, rtol=0)
    torch.testing.assert_close(jet.J, jacobian(q), atol=1e-7, rtol=0)
    with pytest.raises(ValueError, match="holds φ on its"):
        field.jet(q, POINTS[:10])
    with pytest.raises(ValueError, match="order ≤ 1"):
        field.jet(q, POINTS, order=2)


def test_code_box_ignores_non_finite_codes_and_widens():
    codes = torch.tensor([[0.0, 1.0], [float("nan"), 5.0], [1.0, 3.0]])
    low, high = code_box(codes, torch.tensor([[-1.0, 2.0], [0.5, 2.5]]), margin=0.1)
    np.testing.assert_allclose(low, [-1.2, 0.8])
    np.testing.assert_allclose(high, [1.2, 3.2])


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return build_model({"_target_": "lnf.scenes.LiftedPendulum"},
                       {"latent_dim": 1, "width": 16, "depth": 2, "hyper_width": 8, "hyper_depth": 1},
                       {"_target_": "lnf.quadrature.GaussLegendre", "order": 4}).eval()


def test_evaluate_rollouts_gives_the_exact_metrics_through_a_table(model):
    scene = model.scene
    times = 0.05 * np.arange(40)
    states = scene.simulate(np.array([[0.5, 0.0], [1.0, 0.2], [-0.7, 0.4]]), times)
    points = midpoint_grid(12, scene.bounds).numpy()
    fields, velocities = (a.astype(np.float32) for a in scene.fields(states, points))
    runs = {dec: evaluate_rollouts(model, states, times, points, 1.0, true_fields=fields, true_velocities=velocities,
                                   grid_shape=(12, 12), decoding=dec) for dec in ("exact", "tabulated", "auto")}
    assert runs["exact"].metrics["decoding_tabulated"] == 0.0
    assert runs["tabulated"].metrics["decoding_tabulated"] == 1.0
    assert runs["tabulated"].metrics["decoding_table_error"] <= 1e-5
    assert runs["auto"].metrics["decoding_tabulated"] == 1.0  # 120 frames, twice, pay for 16 nodes
    assert runs["exact"].metrics["reduction_tabulated"] == 0.0 and runs["tabulated"].metrics["reduction_tabulated"] == 1.0
    assert runs["tabulated"].metrics["reduction_table_error"] <= 1e-5
    np.testing.assert_allclose(runs["tabulated"].q_ref, runs["exact"].q_ref, rtol=0,
                               atol=1e-4 * np.abs(runs["exact"].q_ref).max())
    scale = np.abs(runs["exact"].pred_fields).max()
    np.testing.assert_allclose(runs["tabulated"].pred_fields, runs["exact"].pred_fields, rtol=0, atol=2e-5 * scale)
    for key in ("field_rel_l2/all/median", "projection_rel_l2/all/max", "energy_rel_err/max"):
        assert runs["tabulated"].metrics[key] == pytest.approx(runs["exact"].metrics[key], rel=1e-3, abs=1e-6)


def test_frame_decoder_refuses_an_unknown_decoding_and_decodes_exactly_when_told(model):
    pts = torch.zeros(4, 2)
    with pytest.raises(ValueError, match="decoding must be one of auto, exact, tabulated, got 'fast'"):
        frame_decoder(model, pts, "fast", torch.zeros(3, 1), 1, 10)
    _, info = frame_decoder(model, pts, "exact", torch.zeros(3, 1), 1, 10 ** 6)
    assert info == {"decoding_tabulated": 0.0}
