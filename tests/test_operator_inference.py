"""Operator Inference baseline (lnf.baselines.operator_inference, through `opinf`) and its study script."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("opinf")

from helpers import split_stand_in  # noqa: E402
from lnf.baselines.operator_inference import REGULARIZERS, OperatorInference  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def oscillators(n, T=40, dt=0.05, seed=0, N=30, loads=None):
    """Two damped linear oscillators lifted to a 1-D field on N points: q(x, t) = Σ_m a_m(t) sin(mπx) (+ a static
    deflection per trajectory's load), fields and velocities (n, T, N, 1); an exact linear discrete map of rank 4."""
    from scipy.linalg import expm

    rng = np.random.default_rng(seed)
    x = (np.arange(N) + 0.5) / N
    modes = np.stack([np.sin(np.pi * x), np.sin(2 * np.pi * x)], 1)
    omega, zeta = np.array([2.0, 5.0]), 0.05
    A = np.zeros((5, 5))  # (a, ȧ, u): the load u pushes both modes and stays constant
    A[:2, 2:4], A[2:4, :2], A[2:4, 2:4] = np.eye(2), -np.diag(omega**2), -np.diag(2 * zeta * omega)
    A[2:4, 4] = [3.0, -1.0]
    P = expm(A * dt)
    y = np.zeros((n, T, 5))
    y[:, 0, :4] = rng.standard_normal((n, 4))
    y[:, 0, 4] = 0.0 if loads is None else loads
    for k in range(T - 1):
        y[:, k + 1] = y[:, k] @ P.T
    fields = np.einsum("ntm,jm->ntj", y[..., :2], modes)[..., None]
    return fields, np.einsum("ntm,jm->ntj", y[..., 2:4], modes)[..., None]


def test_right_rank_reproduces_a_linear_system_and_selects_a_finite_regularizer():
    train, val, test = oscillators(6), oscillators(3, seed=1), oscillators(4, seed=2)
    weights = np.linspace(1.0, 2.0, 30)  # a non-uniform "mass": the weighted POD is still exact at rank 4
    model = OperatorInference(4).fit(*train, 20, *val, point_weights=weights)
    assert model.selection.regularizer in REGULARIZERS and np.isfinite(model.selection.regularizer)
    assert np.isfinite(model.selection.val_error) and model.selection.val_error < 1e-6
    pred = model.predict(test[0][:, 0], test[1][:, 0], 40)  # twice the training horizon
    assert not pred.diverged.any() and pred.rollout_seconds.shape == (4,)
    assert np.linalg.norm(pred.fields - test[0]) / np.linalg.norm(test[0]) < 1e-6
    assert np.linalg.norm(pred.velocities - test[1]) / np.linalg.norm(test[1]) < 1e-6
    assert {c["operators"] for c in model.describe()["candidates"]} == {"cA", "cAH", "cAHG"}
    low = OperatorInference(1).fit(*train, 20, *val)  # too few modes: a worse, but finite, fit
    assert low.selection.val_error > 1e-3
    seeded = OperatorInference(4, svdsolver="randomized").fit(*train, 20, *val)  # the large grids' SVD: as exact
    assert seeded.selection.val_error < 1e-6


def test_per_trajectory_loads_enter_as_inputs():
    rng = np.random.default_rng(3)
    u = {name: rng.uniform(-2, 2, size=(m, 1)) for name, m in (("train", 8), ("val", 3), ("test", 4))}
    train, val, test = (oscillators(len(u[name]), seed=i, loads=u[name][:, 0])
                        for i, name in enumerate(("train", "val", "test")))
    model = OperatorInference(4).fit(*train, 20, *val, controls=u["train"], val_controls=u["val"])
    assert model.selection.operators.endswith("B") and model.selection.val_error < 1e-6
    pred = model.predict(test[0][:, 0], test[1][:, 0], 40, controls=u["test"])
    assert np.linalg.norm(pred.fields - test[0]) / np.linalg.norm(test[0]) < 1e-6
    with pytest.raises(ValueError, match="fitted with loads"):
        model.predict(test[0][:, 0], test[1][:, 0], 40)


def driven_oscillators(params, T=60, dt=0.05, N=30, seed=0):
    """Two damped oscillators lifted to a 1-D field, driven by a load A sin(2π f t) with (A, f) per trajectory
    (params (n, 2)); fine RK4 substeps. Fields and velocities (n, T, N, 1), and the times (T,)."""
    rng = np.random.default_rng(seed)
    x = (np.arange(N) + 0.5) / N
    modes = np.stack([np.sin(np.pi * x), np.sin(2 * np.pi * x)], 1)
    omega, zeta, push = np.array([2.0, 5.0]), 0.05, np.array([3.0, -1.0])

    def rhs(y, t):
        load = params[:, :1] * np.sin(2 * np.pi * params[:, 1:] * t)
        return np.concatenate([y[:, 2:], -omega**2 * y[:, :2] - 2 * zeta * omega * y[:, 2:] + load * push], 1)

    y, h, out = rng.standard_normal((len(params), 4)), dt / 20, []
    for k in range(T):
        out.append(y)
        for j in range(20):
            t = k * dt + j * h
            k1 = rhs(y, t); k2 = rhs(y + h / 2 * k1, t + h / 2); k3 = rhs(y + h / 2 * k2, t + h / 2)
            y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + rhs(y + h * k3, t + h))
    y = np.stack(out, 1)
    return (np.einsum("ntm,jm->ntj", y[..., :2], modes)[..., None], np.einsum("ntm,jm->ntj", y[..., 2:], modes)[..., None],
            np.arange(T) * dt)


def test_time_varying_loads_enter_as_input_series_held_over_each_step():
    """A load A sin(2π f t) is given as its series u(t_k) (Scene.input_signals), each step with (u_k, u_{k+1});
    the per-trajectory parameters (A, f) held constant cannot describe it."""
    from lnf.scenes import ElasticCantilever

    rng = np.random.default_rng(4)
    params = {name: np.column_stack([rng.uniform(-2, 2, m), rng.uniform(0.3, 0.7, m)])
              for name, m in (("train", 10), ("val", 3), ("test", 4))}
    data = {name: driven_oscillators(p, seed=i) for i, (name, p) in enumerate(params.items())}
    times = data["train"][2]
    series = {name: ElasticCantilever.input_signals(None, p, times) for name, p in params.items()}
    assert series["train"].shape == (10, 60, 1)
    np.testing.assert_allclose(series["train"][3, 7, 0], params["train"][3, 0] * np.sin(2 * np.pi * params["train"][3, 1] * times[7]))
    fit = dict(controls=series["train"], val_controls=series["val"])
    model = OperatorInference(4).fit(*data["train"][:2], 30, *data["val"][:2], **fit)
    assert model.n_inputs == 2  # (u_k, u_{k+1})
    test = data["test"]
    pred = model.predict(test[0][:, 0], test[1][:, 0], 60, controls=series["test"])
    error = np.linalg.norm(pred.fields - test[0]) / np.linalg.norm(test[0])
    constant = OperatorInference(4).fit(*data["train"][:2], 30, *data["val"][:2], controls=params["train"],
                                        val_controls=params["val"])
    held = constant.predict(test[0][:, 0], test[1][:, 0], 60, controls=params["test"])
    held_error = np.linalg.norm(held.fields - test[0]) / np.linalg.norm(test[0])
    assert error < 0.01 and (held.diverged.any() or held_error > 10 * error)  # 0.0024 against diverged rollouts
    with pytest.raises(ValueError, match=r"controls give 1 inputs per step, the model was fitted with 2"):
        model.predict(test[0][:, 0], test[1][:, 0], 60, controls=params["test"][:, :1])
    with pytest.raises(ValueError, match=r"controls must be loads per trajectory \(4, c\) or input series \(4, ≥60, c\)"):
        model.predict(test[0][:, 0], test[1][:, 0], 60, controls=series["test"][:, :10])


def test_the_study_gives_a_scene_s_input_series_only_where_the_scene_defines_them():
    """A scene whose loads vary in time gives Operator Inference its series; one with constant loads (no
    input_signals of its own) its parameters (n, c), not a held series whose steps would repeat each input."""
    from experiments.operator_inference import split_controls
    from lnf.scenes import ElasticCantilever, Scene

    class ConstantLoads(Scene):
        def controls(self, states):
            return states[:, -1:]

    split = split_stand_in(controls=None, states=np.array([[[0.0, 2.0]], [[0.0, -1.0]]]), times=np.arange(5) * 0.1)
    np.testing.assert_array_equal(split_controls(ConstantLoads.__new__(ConstantLoads), split), [[2.0], [-1.0]])
    stored = split_stand_in(controls=np.array([[0.5, 0.4]]), states=np.zeros((1, 5, 0)), times=split.times)
    series = split_controls(ElasticCantilever.__new__(ElasticCantilever), stored)
    np.testing.assert_allclose(series[0, :, 0], 0.5 * np.sin(2 * np.pi * 0.4 * split.times))


def test_blown_up_rollouts_are_marked_diverged_not_raised():
    train, val = oscillators(6), oscillators(3, seed=1)
    model = OperatorInference(4, operators=["cA"], regularizers=[1e-8]).fit(*train, 20, *val)
    model.model.A_.entries = 3.0 * np.eye(4)  # an unstable map: the rollout leaves any bound
    pred = model.predict(val[0][:, 0], val[1][:, 0], 200)
    assert pred.diverged.all() and np.isnan(pred.fields[:, -1]).all() and np.isfinite(pred.fields[:, 0]).all()


@pytest.mark.parametrize("rank, match", [(0, "rank must be an integer ≥ 1"), (-2, "rank must be an integer ≥ 1"),
                                         (2.5, "rank must be an integer ≥ 1")])
def test_a_bad_rank_is_refused_at_construction(rank, match):
    with pytest.raises(ValueError, match=match):
        OperatorInference(rank)


def test_a_rank_beyond_the_snapshots_is_refused_naming_them():
    train, val = oscillators(2, T=10), oscillators(1, seed=1, T=10)
    with pytest.raises(ValueError, match=r"rank 9 is larger than the training snapshots allow: 8 snapshots "
                                         r"\(2 trajectories × 4 samples\)"):
        OperatorInference(9).fit(*train, 4, *val)
    with pytest.raises(ValueError, match="must be an integer ≥ 1"):
        OperatorInference(True)


def test_without_opinf_the_error_names_the_extra(monkeypatch):
    from lnf.baselines.operator_inference import import_opinf

    monkeypatch.setitem(sys.modules, "opinf", None)
    with pytest.raises(ImportError, match=r"baselines` extra, `pip install -e \"\.\[baselines\]\"`"):
        import_opinf()


def test_study_script_refuses_a_bad_rank_before_any_data(tmp_path, monkeypatch):
    from experiments import operator_inference as script

    monkeypatch.setenv("LNF_DATA_DIR", str(tmp_path / "data"))
    with pytest.raises(SystemExit, match="--ranks: a rank must be an integer ≥ 1, got 0"):
        script.main(["--smoke", "--scene", "pendulum", "--ranks", "2", "0", "--out", str(tmp_path / "out")])
    assert not (tmp_path / "data").exists() and not (tmp_path / "out").exists()


@pytest.mark.slow
def test_study_script_smoke_on_the_pendulum(tmp_path):
    env = {**os.environ, "LNF_DATA_DIR": str(tmp_path / "data")}
    out = tmp_path / "opinf"
    proc = subprocess.run([sys.executable, "-m", "experiments.operator_inference", "--smoke", "--scene", "pendulum",
                           "--ranks", "1", "2", "--observed", "--out", str(out)], cwd=ROOT, capture_output=True, text=True,
                          timeout=300, env=env)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = (out / "summary.md").read_text()
    assert summary.startswith("Machine: ") and "Command: `python -m experiments.operator_inference --smoke" in summary
    assert "| method | rank r | operators |" in summary and "| OpInf | 2 |" in summary
    rows = json.loads((out / "operator_inference.json").read_text())["rows"]
    # each rank on the full states, then on the sparse observations (gappy POD, completion rank 2 under --smoke)
    assert [(r["method"], r["rank"]) for r in rows] == [("OpInf", 1), ("OpInf (observed)", 1), ("OpInf", 2),
                                                        ("OpInf (observed)", 2)]
    assert "| OpInf (observed) | 2 |" in summary and all(r["completion_rank"] == 2 for r in rows[1::2])
    for r in rows:
        for window in ("all", "in_horizon", "extrapolation"):
            assert np.isfinite(r[f"field_rel_l2/{window}/median"])
        assert r["diverged"] == 0 and r["fit_seconds"] > 0 and r["operators"] in ("cA", "cAH", "cAHG")
    assert list((tmp_path / "data").glob("pendulum-*.h5"))
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name]
