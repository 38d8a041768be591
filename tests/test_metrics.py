"""docs/method.md §7.3 metrics on hand-made arrays, and the evaluation point subset."""
import numpy as np
import pytest

from lnf import metrics as M
from lnf.evaluation import reduction_subset


def test_field_rel_l2_windows_and_values():
    times = 0.05 * np.arange(100)
    true = np.ones((2, 100, 4, 1))
    pred = true.copy()
    pred[0, 50:] *= 1.1  # 10 % error after the horizon only
    out = M.field_metrics("field_rel_l2", pred, true, np.full(4, 0.25), times, 2.5)
    assert out["field_rel_l2/in_horizon/max"] == pytest.approx(0.0)
    assert out["field_rel_l2/extrapolation/max"] == pytest.approx(0.1)
    assert out["field_rel_l2/all/max"] == pytest.approx(np.sqrt(50 * 0.01 / 100))
    assert out["field_rel_l2/extrapolation/median"] == pytest.approx(0.05)


def test_vpt_first_crossing_and_horizon():
    times = 0.1 * np.arange(10)
    true = np.ones((2, 10, 3, 1))
    pred = true.copy()
    pred[0, 4:] += 0.5  # frame MSE 0.25 > 0.025 from t = 0.4
    vpt = M.valid_prediction_time(pred, true, np.ones(3), times)
    assert vpt[0] == pytest.approx(0.4) and vpt[1] == pytest.approx(1.0)
    pred[1, 2] = np.nan  # a diverged frame counts as invalid
    assert M.valid_prediction_time(pred, true, np.ones(3), times)[1] == pytest.approx(0.2)


def test_energy_metrics_and_nan_as_failure():
    e_true = np.full((2, 5), 2.0)
    e_pred = np.array([[2.0, 2.1, 2.2, 2.1, 2.0], [2.0, np.nan, 2.0, 2.0, 2.0]])
    out = M.energy_metrics(e_pred, e_true, 10.0)
    assert out["energy_drift/median"] == pytest.approx(0.02) or np.isinf(out["energy_drift/max"])
    assert np.isinf(out["energy_rel_err/max"])  # a NaN (diverged) trajectory is reported as inf, not hidden


def test_reduction_subset_is_strided_grid():
    idx = reduction_subset(64 * 64, (64, 64), 1024)
    assert len(idx) == 1024
    grid = np.arange(4096).reshape(64, 64)
    assert set(idx) == set(grid[::2, ::2].reshape(-1))
    assert len(reduction_subset(100, None, 1024)) == 100
    assert len(reduction_subset(5000, None, 1000)) == 1000
