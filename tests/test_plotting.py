"""Tests for lnf.plotting (Figure 3 of the paper and the atomic PNG writer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from lnf import plotting
from lnf.plotting import (
    default_snapshot_indices,
    field_snapshots_figure,
    figure3,
    latent_and_energy_figure,
    save_figure,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
H = 2.5  # training horizon [s]
G = (16, 16)
BOUNDS = ((-1.0, 1.0), (-1.0, 1.0))


@pytest.fixture(scope="module")
def data():
    """Synthetic lifted-pendulum-like data: q(X, t) = u(X) θ(t) on a 16×16 grid."""
    t = 0.05 * np.arange(100)
    w = np.sqrt(9.81)
    theta = 0.8 * np.cos(w * t)
    theta_dot = -0.8 * w * np.sin(w * t)
    q_proj = theta[:, None]
    q_pred = (0.8 * np.cos(1.01 * w * t))[:, None]  # slightly detuned rollout
    x = np.linspace(-1, 1, G[0])
    y = np.linspace(-1, 1, G[1])
    X, Y = np.meshgrid(x, y, indexing="ij")
    u = (0.5 * (5 * X**3 - 3 * X)) * (0.125 * (35 * Y**4 - 30 * Y**2 + 3))
    u = u.reshape(-1)
    energies = {
        "kinetic_true": 0.5 * theta_dot**2,
        "potential_true": 9.81 * (1 - np.cos(theta)),
        "kinetic_pred": 0.5 * (0.8 * 1.01 * w * np.sin(1.01 * w * t)) ** 2,
        "potential_pred": 9.81 * (1 - np.cos(q_pred[:, 0])),
    }
    return dict(
        t=t,
        q_pred=q_pred,
        q_proj=q_proj,
        energies=energies,
        pred_fields=q_pred[:, :1] * u[None, :],
        true_fields=q_proj[:, :1] * u[None, :],
    )


def _assert_png(path, min_bytes=5_000):
    assert path.exists()
    raw = path.read_bytes()
    assert raw[:8] == PNG_MAGIC
    assert len(raw) > min_bytes
    leftovers = [p.name for p in path.parent.iterdir() if "tmp" in p.name]
    assert leftovers == []


def _close(fig):
    fig.clear()


def test_default_snapshot_indices_paper_grid():
    t = 0.05 * np.arange(100)
    assert default_snapshot_indices(t, 2.5) == [12, 37, 62, 87]
    idx = default_snapshot_indices(t, 2.5, n_each=3)
    assert len(idx) == 6 and all(t[i] < 2.5 for i in idx[:3]) and all(t[i] >= 2.5 for i in idx[3:])
    # horizon past the end: only "before" samples
    assert all(i < 100 for i in default_snapshot_indices(t, 10.0))
    assert len(default_snapshot_indices(t, 10.0)) == 2
    with pytest.raises(ValueError, match="n_each"):
        default_snapshot_indices(t, 2.5, n_each=0)


def test_latent_and_energy_figure_saves(tmp_path, data):
    e = data["energies"]
    fig = latent_and_energy_figure(
        data["t"], data["q_pred"], data["q_proj"], e["kinetic_pred"], e["potential_pred"],
        e["kinetic_true"], e["potential_true"], train_horizon=H, title="latent",
    )
    assert isinstance(fig, Figure)
    ax_q, ax_e = fig.axes[:2]
    assert ax_q.get_xlabel() == "t [s]" and "[J]" in ax_e.get_ylabel()
    assert ax_q.get_legend() is not None and ax_e.get_legend() is not None
    out = save_figure(fig, tmp_path / "sub" / "latent.png")  # parent dir created
    _assert_png(out)


def test_latent_accepts_multi_dim_and_1d(tmp_path, data):
    t = data["t"]
    q = np.stack([np.sin(t), np.cos(t), t / 5], axis=1)
    e = data["energies"]
    fig = latent_and_energy_figure(t, q, q + 0.01, e["kinetic_pred"], e["potential_pred"],
                                   e["kinetic_true"], e["potential_true"], H)
    _assert_png(save_figure(fig, tmp_path / "multi.png"))
    fig = latent_and_energy_figure(t, q[:, 0], q[:, 0], e["kinetic_pred"], e["potential_pred"],
                                   e["kinetic_true"], e["potential_true"], H)
    assert isinstance(fig, Figure)


def test_field_snapshots_figure_saves(tmp_path, data):
    idx = [12, 37, 62, 87]
    fig = field_snapshots_figure(G, BOUNDS, list(data["t"][idx]), data["pred_fields"][idx],
                                 data["true_fields"][idx], H, title="fields")
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    assert sum("before horizon" in s for s in titles) == 2
    assert sum("after horizon" in s for s in titles) == 2
    # 12 image panels + 2 colour bars
    assert len(fig.axes) == 14
    # x is horizontal: the image is (ny, nx) with extent from bounds
    im = fig.axes[0].images[0]
    assert im.get_array().shape == (G[1], G[0])
    assert tuple(im.get_extent()) == (-1.0, 1.0, -1.0, 1.0)
    _assert_png(save_figure(fig, tmp_path / "fields.png"))


def test_field_snapshots_non_square_grid_orientation():
    nx, ny = 8, 5
    x = np.linspace(0, 1, nx)
    field = np.repeat(x, ny)[None, :]  # 'ij' row-major: varies along x only
    fig = field_snapshots_figure((nx, ny), (0, 2, 0, 1), [1.0], field, field, 2.5)
    arr = fig.axes[0].images[0].get_array()
    assert arr.shape == (ny, nx)
    np.testing.assert_allclose(arr[0], x)  # a row of the image runs along x


def test_figure3_saves_and_overwrites(tmp_path, data):
    fig = figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], G, BOUNDS,
                  data["pred_fields"], data["true_fields"], [12, 37, 62, 87], H, title="fig3")
    path = tmp_path / "fig3.png"
    _assert_png(save_figure(fig, path), min_bytes=20_000)
    # default indices (built, not rendered: rendering is the slow part)
    fig = figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], G, BOUNDS,
                  data["pred_fields"], data["true_fields"], None, H)
    titles = [ax.get_title() for ax in fig.axes]
    for t in (0.6, 1.85, 3.1, 4.35):  # samples 12, 37, 62, 87
        assert any(f"t = {t:.3g} s" in s for s in titles)
    # overwrite of an existing file
    small = Figure(figsize=(2, 2))
    small.add_subplot().plot([0, 1], [1, 0])
    _assert_png(save_figure(small, path), min_bytes=1_000)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig3.png"]


def test_nan_predictions_still_plot(tmp_path, data):
    q_pred = data["q_pred"].copy()
    q_pred[60:] = np.nan  # rollout diverged after the horizon
    q_pred[55] = np.inf
    e = {k: v.copy() for k, v in data["energies"].items()}
    e["kinetic_pred"][60:] = np.nan
    e["potential_pred"][58:] = np.inf
    pred_fields = data["pred_fields"].copy()
    pred_fields[60:] = np.nan
    pred_fields[37, :10] = np.nan
    fig = figure3(data["t"], q_pred, data["q_proj"], e, G, BOUNDS, pred_fields,
                  data["true_fields"], [12, 37, 62, 87], H)
    _assert_png(save_figure(fig, tmp_path / "nan.png"))
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert any("non-finite" in s for s in texts)  # shown, not hidden
    # entirely non-finite prediction: still plots
    fig = field_snapshots_figure(G, BOUNDS, [3.0], np.full((1, 256), np.nan),
                                 data["true_fields"][:1], H)
    _assert_png(save_figure(fig, tmp_path / "allnan.png"))


@pytest.mark.parametrize(
    "kwargs, argname",
    [
        (dict(q_pred=np.zeros((99, 1))), "q_pred"),
        (dict(q_proj=np.zeros((100, 2))), "q_proj"),
        (dict(kinetic_true=np.zeros(50)), "kinetic_true"),
        (dict(potential_pred=np.zeros((100, 1))), "potential_pred"),
        (dict(times=np.zeros((100, 1))), "times"),
        (dict(train_horizon=float("nan")), "train_horizon"),
    ],
)
def test_latent_shape_errors(data, kwargs, argname):
    e = data["energies"]
    args = dict(times=data["t"], q_pred=data["q_pred"], q_proj=data["q_proj"],
                kinetic_pred=e["kinetic_pred"], potential_pred=e["potential_pred"],
                kinetic_true=e["kinetic_true"], potential_true=e["potential_true"], train_horizon=H)
    args.update(kwargs)
    with pytest.raises(ValueError, match=argname):
        latent_and_energy_figure(**args)


def test_latent_error_message_is_explicit(data):
    e = data["energies"]
    with pytest.raises(ValueError) as exc:
        latent_and_energy_figure(data["t"], np.zeros((99, 1)), data["q_proj"], e["kinetic_pred"],
                                 e["potential_pred"], e["kinetic_true"], e["potential_true"], H)
    msg = str(exc.value)
    assert "q_pred" in msg and "(T, d)" in msg and "100" in msg and "(99, 1)" in msg


@pytest.mark.parametrize(
    "kwargs, argname",
    [
        (dict(pred=np.zeros((2, 256))), "pred"),
        (dict(true=np.zeros((3, 255))), "true"),
        (dict(grid_shape=(16, 0)), "grid_shape"),
        (dict(grid_shape=(16,)), "grid_shape"),
        (dict(bounds=(0, 1, 0)), "bounds"),
        (dict(bounds=(1, 0, 0, 1)), "bounds"),
        (dict(times_shown=[]), "times_shown"),
    ],
)
def test_field_shape_errors(kwargs, argname):
    args = dict(grid_shape=G, bounds=BOUNDS, times_shown=[0.5, 1.0, 3.0],
                pred=np.zeros((3, 256)), true=np.zeros((3, 256)), train_horizon=H)
    args.update(kwargs)
    with pytest.raises(ValueError, match=argname):
        field_snapshots_figure(**args)


@pytest.mark.parametrize(
    "kwargs, argname",
    [
        (dict(pred_fields=np.zeros((100, 200))), "pred_fields"),
        (dict(true_fields=np.zeros((99, 256))), "true_fields"),
        (dict(energies={"kinetic_pred": np.zeros(100)}), "energies"),
        (dict(snapshot_indices=[0, 100]), "snapshot_indices"),
        (dict(snapshot_indices=[]), "snapshot_indices"),
    ],
)
def test_figure3_shape_errors(data, kwargs, argname):
    args = dict(times=data["t"], q_pred=data["q_pred"], q_proj=data["q_proj"], energies=data["energies"],
                grid_shape=G, bounds=BOUNDS, pred_fields=data["pred_fields"],
                true_fields=data["true_fields"], snapshot_indices=[12, 87], train_horizon=H)
    args.update(kwargs)
    with pytest.raises(ValueError, match=argname):
        figure3(**args)


def test_save_figure_cleans_up_on_failure(tmp_path, monkeypatch):
    fig = Figure()
    fig.add_subplot().plot([0, 1], [0, 1])

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(plotting.os, "replace", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        save_figure(fig, tmp_path / "x.png")
    assert list(tmp_path.iterdir()) == []


def test_save_figure_png_whatever_suffix(tmp_path):
    fig = Figure()
    fig.add_subplot().plot([0, 1], [0, 1])
    out = save_figure(fig, str(tmp_path / "plot.pdf"))
    assert out == tmp_path / "plot.pdf"
    assert out.read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(ValueError, match="fig"):
        save_figure("not a figure", tmp_path / "y.png")


def test_no_pyplot_import():
    """lnf.plotting never imports pyplot (no display needed, no global figure state)."""
    import ast

    tree = ast.parse(Path(plotting.__file__).read_text(encoding="utf-8"))
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            imported.add(node.module or "")
            imported.update(f"{node.module}.{a.name}" for a in node.names)
    assert not any("pyplot" in name for name in imported), imported


@pytest.mark.parametrize("grid_shape, bounds", [((32,), [[0.0, 1.0]]), ((6, 5, 4), [[0, 1], [0, 1], [0, 0.5]])],
                         ids=["1-D body", "3-D body"])
def test_figure3_draws_bodies_of_one_and_three_dimensions(data, grid_shape, bounds, tmp_path):
    """A 1-D body gets space–time images and snapshot lines, a 3-D body its middle slice (a 1-D body used to
    raise 'grid_shape must be a pair')."""
    n = int(np.prod(grid_shape))
    rng = np.random.default_rng(0)
    true = rng.standard_normal((100, n))
    fig = figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], grid_shape, bounds,
                  true + 0.1, true, None, H, title="body")
    path = save_figure(fig, tmp_path / "f.png")
    assert path.read_bytes()[:8] == PNG_MAGIC
    labels = [ax.get_xlabel() for ax in fig.axes]
    assert "x" in labels
    if len(grid_shape) == 1:
        assert any("training horizon" in ax.get_ylabel() for ax in fig.axes)
    else:
        assert any("slice z" in (ax.get_ylabel() or "") for ax in fig.axes)
    wrong = [[0.0, 1.0]] * (len(grid_shape) % 3 + 1)  # bounds of another dimension than the grid's
    with pytest.raises(ValueError, match="bounds"):
        figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], grid_shape, wrong, true, true, None, H)
