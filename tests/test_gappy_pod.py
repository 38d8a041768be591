"""Gappy POD (lnf.baselines.gappy_pod) and the "OpInf (observed)" variant (experiments/opinf_observed.py)."""
import numpy as np
import pytest

from helpers import split_stand_in
from lnf.baselines.gappy_pod import complete_snapshots, gappy_encode, interpolation_matrix, select_rank


def low_rank(n=8, T=15, Nc=40, A=2, rank=3, fraction=0.4, seed=0):
    """A rank-`rank` field (plus a mean) on Nc points of [0, 1], smooth in space; each trajectory observes a fixed
    random `fraction` of the points. values (n, T, Nc, A), masks (n, Nc), points (Nc,)."""
    rng = np.random.default_rng(seed)
    x = np.sort(rng.random(Nc))
    modes = np.stack([np.sin((k + 1) * np.pi * x[:, None] + a) for k in range(rank) for a in range(A)], 0)
    modes = modes.reshape(rank, A, Nc).transpose(0, 2, 1)  # (rank, Nc, A)
    values = 0.5 + np.einsum("ntk,kpa->ntpa", rng.standard_normal((n, T, rank)), modes)
    masks = np.zeros((n, Nc), dtype=bool)
    for i in range(n):
        masks[i, rng.choice(Nc, int(fraction * Nc), replace=False)] = True
    return values, masks, x


def test_completion_recovers_a_low_rank_dataset_from_40_percent_of_the_points():
    values, masks, x = low_rank()
    gappy = np.where(masks[:, None, :, None], values, np.nan)  # unobserved entries are never read
    seen = masks.any(0)
    done, info = complete_snapshots(gappy, masks, 3, points=x, ridge=0.0)  # no ridge: the exact fixed point
    assert info["converged"] and info["unobserved_points"] == int((~seen).sum())
    np.testing.assert_array_equal(done[masks[:, None, :, None].repeat(15, 1).repeat(2, 3)],
                                  values[masks[:, None, :, None].repeat(15, 1).repeat(2, 3)])
    err = np.linalg.norm((done - values)[:, :, seen]) / np.linalg.norm(values[:, :, seen])
    assert err < 1e-5 and info["basis"].shape == (80, 3) and info["mean"].shape == (80,)
    assert np.all(np.isfinite(done))  # a point nobody observes: interpolated from its neighbours
    ridged = complete_snapshots(gappy, masks, 3, points=x)[0]  # the default ridge: biased by less than 1e-3
    assert np.linalg.norm((ridged - values)[:, :, seen]) / np.linalg.norm(values[:, :, seen]) < 1e-3
    start = np.linalg.norm((np.where(masks[:, None, :, None], values, values.mean((0, 1))) - values)[:, :, seen])
    svd = complete_snapshots(gappy, masks, 3, method="svd")[0]  # Everson & Sirovich's sweeps: slower, same way
    assert np.linalg.norm((svd - values)[:, :, seen]) < 0.5 * start
    rank, errors = select_rank(gappy, masks, [2, 3, 4], points=x)
    assert rank == 3 and errors[3] < 1e-4 < errors[2]


def test_the_ridge_keeps_a_rank_above_the_datas_from_drifting():
    """Rank 7 on rank-3 data seen through 25 % masks: rows of U that too few trajectories determine drift without
    the ridge (a relative error of several units after 300 sweeps); the default ridge holds them near the data."""
    values, masks, x = low_rank(fraction=0.25)
    seen = masks.any(0)

    def error(ridge):
        done = complete_snapshots(values, masks, 7, points=x, ridge=ridge, iterations=300)[0]
        return np.linalg.norm((done - values)[:, :, seen]) / np.linalg.norm(values[:, :, seen])

    free, ridged = error(0.0), error(1e-5)
    assert free > 1.0 and ridged < 0.2 * free


def test_gappy_encode_recovers_the_coefficients_of_a_vector_in_the_span():
    rng = np.random.default_rng(1)
    basis, mean, c = rng.standard_normal((50, 4)), rng.standard_normal(50), rng.standard_normal((3, 4))
    observed = np.zeros(50, dtype=bool)
    observed[rng.choice(50, 6, replace=False)] = True
    values = c @ basis.T + mean
    values[:, ~observed] = np.nan  # never read
    np.testing.assert_allclose(gappy_encode(basis, mean, values, observed), c, atol=1e-10)
    np.testing.assert_allclose(gappy_encode(basis, mean, values[0], observed, weights=rng.random(50) + 0.1), c[0],
                               atol=1e-10)
    with pytest.raises(ValueError, match="at least r = 4 observed entries"):
        gappy_encode(basis, mean, values, observed & (np.cumsum(observed) <= 3))


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_interpolation_reproduces_linear_functions_and_rows_sum_to_one(dim):
    rng = np.random.default_rng(dim)
    corners = np.array(np.meshgrid(*[[0.0, 1.0]] * dim, indexing="ij")).reshape(dim, -1).T
    source = np.concatenate([corners, rng.random((25, dim))])  # the hull: the unit cube
    inside, outside = rng.random((40, dim)), 1.5 + rng.random((5, dim))
    W = interpolation_matrix(source, np.concatenate([inside, outside]))
    assert W.shape == (45, len(source))
    np.testing.assert_allclose(np.asarray(W.sum(1)).ravel(), 1.0)
    slope = np.arange(1.0, dim + 1)
    f = lambda p: 2.0 + p @ slope  # noqa: E731
    np.testing.assert_allclose((W @ f(source))[:40], f(inside), atol=1e-12)
    nearest = np.argmin(np.linalg.norm(outside[:, None] - source[None], axis=2), axis=1)
    np.testing.assert_allclose((W @ f(source))[40:], f(source[nearest]))  # outside: the nearest source
    if dim == 1:  # 1-D points may come flat
        np.testing.assert_allclose(interpolation_matrix(source[:, 0], inside[:, 0]) @ f(source), f(inside))


def test_bad_shapes_name_the_argument():
    values, masks, _ = low_rank()
    with pytest.raises(ValueError, match=r"values must be \(n, T, Nc, A\)"):
        complete_snapshots(values[0], masks, 3)
    with pytest.raises(ValueError, match=r"masks must be \(n, Nc\) = \(8, 40\) bool"):
        complete_snapshots(values, masks[:, :10], 3)
    with pytest.raises(ValueError, match=r"rank must be an integer in \[1, 80\]"):
        complete_snapshots(values, masks, 81)
    with pytest.raises(ValueError, match=r"points must be \(Nc, dim\)"):
        complete_snapshots(values, masks, 3, points=np.zeros(5))
    with pytest.raises(ValueError, match=r"mean must be \(D,\) = \(50,\)"):
        gappy_encode(np.zeros((50, 2)), np.zeros(49), np.zeros(50), np.ones(50, bool))
    with pytest.raises(ValueError, match=r"observed must be \(D,\) = \(50,\) bool"):
        gappy_encode(np.zeros((50, 2)), np.zeros(50), np.zeros(50), np.ones(50))
    with pytest.raises(ValueError, match=r"target_points must be \(Nf, 2\)"):
        interpolation_matrix(np.zeros((5, 2)), np.zeros((3, 3)))


def test_opinf_observed_end_to_end_on_a_tiny_standing_wave(monkeypatch):
    pytest.importorskip("opinf")
    from test_operator_inference import oscillators

    from experiments import opinf_observed

    monkeypatch.setattr(opinf_observed, "COMPLETION_RANKS", (3, 4, 5))  # fewer candidates: a faster test

    rng = np.random.default_rng(4)

    def split(n, seed):
        fine, coarse = oscillators(n, seed=seed, N=30), oscillators(n, seed=seed, N=16)
        masks = np.zeros((n, 16), dtype=bool)
        for i in range(n):
            masks[i, rng.choice(16, 8, replace=False)] = True
        return split_stand_in(times=0.05 * np.arange(40), fine_points=((np.arange(30) + 0.5) / 30)[:, None],
                              coarse_points=((np.arange(16) + 0.5) / 16)[:, None], states=np.zeros((n, 40, 0)),
                              fields=fine[0], velocities=fine[1], coarse_fields=coarse[0],
                              coarse_velocities=coarse[1], masks=masks, weights=None, controls=None, train_times=20)

    splits = {"train": split(4, 0), "val": split(1, 1), "test": split(2, 2)}
    out = opinf_observed.evaluate_observed(None, splits, 4)
    assert out["method"] == "OpInf (observed)" and out["rank"] == 4 and out["trajectories"] == 2
    assert out["diverged"] == 0 and out["completion_rank"] == 4  # [q, s q̇] of two modes: rank 4
    for key in ("field_rel_l2/all/median", "field_rel_l2/in_horizon/median", "field_rel_l2/extrapolation/median",
                "velocity_rel_l2/all/median", "projection_rel_l2/all/median", "gappy_projection_rel_l2/all/median"):
        assert 0 <= out[key] < 0.3, (key, out[key])
    # the floor: linear interpolation 16 → 30 points (≈ 3 %); the full-state OpInf is exact here
    assert out["field_rel_l2/all/median"] < 0.1 and out["projection_rel_l2/all/median"] < 0.1
    assert out["fit_seconds"] > 0 and out["rollout_seconds_per_trajectory"] > 0
    assert out["decode_seconds_per_trajectory"] >= 0
