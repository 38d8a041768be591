"""Tests for lnf.plotting (Figure 3 of the paper and the atomic PNG + PDF writer)."""

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
PDF_MAGIC = b"%PDF"
H = 2.5  # training horizon [s]
G = (16, 16)
BOUNDS = ((-1.0, 1.0), (-1.0, 1.0))


@pytest.fixture(autouse=True)
def vector_figures(monkeypatch):
    """The suite writes PNGs alone (conftest.py); these tests check the PDF beside each PNG too."""
    monkeypatch.setenv("LNF_FIGURE_PDF", "1")


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
    assert plotting.vector_path(path).read_bytes()[:4] == PDF_MAGIC  # the vector copy beside it
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
    assert ax_q.get_xlabel() == "time t [s]" and "[J]" in ax_e.get_ylabel()
    assert ax_q.get_ylabel() == "latent coordinate q̃"
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
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig3.pdf", "fig3.png"]  # the vector copy beside it


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

    monkeypatch.setattr(plotting.save.os, "replace", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        save_figure(fig, tmp_path / "x.png")
    assert list(tmp_path.iterdir()) == []


def test_save_figure_png_whatever_suffix(tmp_path):
    fig = Figure()
    fig.add_subplot().plot([0, 1], [0, 1])
    out = save_figure(fig, str(tmp_path / "plot.pdf"))
    assert out == tmp_path / "plot.pdf"
    assert out.read_bytes()[:8] == PNG_MAGIC
    # the PDF cannot take the PNG's name: it gets its own
    assert plotting.vector_path(out) == tmp_path / "plot.vector.pdf"
    assert (tmp_path / "plot.vector.pdf").read_bytes()[:4] == PDF_MAGIC
    with pytest.raises(ValueError, match="fig"):
        save_figure("not a figure", tmp_path / "y.png")


def test_no_pyplot_import():
    """lnf.plotting never imports pyplot (no display needed, no global figure state)."""
    import ast

    trees = [ast.parse(f.read_text(encoding="utf-8")) for f in sorted(Path(plotting.__file__).parent.glob("*.py"))]
    imported = set()
    for node in (n for tree in trees for n in ast.walk(tree)):
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
    assert "X₁" in labels and "time t [s]" in labels  # body coordinates and time, in words
    if len(grid_shape) == 1:
        assert any("training horizon" in ax.get_ylabel() for ax in fig.axes)
    else:
        assert any("slice X₃" in (ax.get_ylabel() or "") for ax in fig.axes)
        assert any(ax.get_ylabel().endswith("X₂") for ax in fig.axes)
    wrong = [[0.0, 1.0]] * (len(grid_shape) % 3 + 1)  # bounds of another dimension than the grid's
    with pytest.raises(ValueError, match="bounds"):
        figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], grid_shape, wrong, true, true, None, H)


# --------------------------------------------------------------------------------------
# fields on scattered points (grid_shape=None, points=...)
# --------------------------------------------------------------------------------------


def _figure3_on_points(data, points, bounds, pred, true, idx, **kw):
    return figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], None, bounds, pred, true,
                   idx, H, points=points, **kw)


def _colorbar_labels(fig):
    return [ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>"]


def test_figure3_scattered_1d_points_unsorted_non_uniform(data, tmp_path):
    """Unsorted, non-uniformly spaced points of a 1-D body: drawn sorted by x, each cell reaching halfway to
    its neighbours (the outer cells clipped to the box), the line plots through the sorted points."""
    x = np.array([0.9, 0.05, 0.5, 0.1, 0.2, 0.97, 0.0, 0.7])  # unsorted, clustered near 0
    xs = np.sort(x)
    true = data["q_proj"] * np.sin(3 * x)[None, :]
    pred = true + 0.1 * x[None, :]
    fig = _figure3_on_points(data, x[:, None], [[0.0, 1.0]], pred, true, [12, 62], title="1-D points")
    path = save_figure(fig, tmp_path / "scattered_1d.png")
    _assert_png(path, min_bytes=20_000)
    # latent, total energy, energy exchange; 3 space–time panels + their 3 colour bars, 1 line-plot panel
    assert len(fig.axes) == 10
    assert _colorbar_labels(fig) == ["field q", "field q", plotting.style._ERROR_LABEL]
    mesh = fig.axes[3].collections[0]  # the "predicted" space–time panel
    assert fig.axes[3].get_title() == "predicted"
    coords = mesh.get_coordinates()  # (T + 1, N + 1, 2) cell corners
    edges = np.concatenate([[0.0], 0.5 * (xs[1:] + xs[:-1]), [1.0]])  # x = 0 is a point: its cell starts there
    np.testing.assert_allclose(coords[0, :, 0], edges)
    assert coords[0, 0, 1] == data["t"][0] and coords[-1, 0, 1] == data["t"][-1]
    np.testing.assert_allclose(np.asarray(mesh.get_array()).reshape(100, 8), pred[:, np.argsort(x)])
    line_ax = fig.axes[-1]
    assert "solid: predicted" in line_ax.get_ylabel()
    np.testing.assert_array_equal(line_ax.lines[0].get_xdata(), xs)
    np.testing.assert_allclose(line_ax.lines[0].get_ydata(), pred[12, np.argsort(x)])


def test_figure3_scattered_2d_random_points_with_nan_block(data, tmp_path):
    """Random points of a 2-D body, the prediction NaN on a block after the horizon: tripcolor panels, grey
    (NaN) triangles exactly where a vertex is non-finite, the share noted, the box as axis limits."""
    rng = np.random.default_rng(3)
    pts = rng.uniform([-1.0, 0.0], [1.0, 2.0], size=(200, 2))
    u = np.sin(np.pi * pts[:, 0]) * np.cos(pts[:, 1])
    true = data["q_proj"] * u[None, :]
    pred = 1.05 * true
    block = (pts[:, 0] > 0.3) & (pts[:, 1] > 1.0)
    pred[60:, block] = np.nan
    fig = _figure3_on_points(data, pts, [[-1.0, 1.0], [0.0, 2.0]], pred, true, [12, 87],
                             field_label="field q₃")
    _assert_png(save_figure(fig, tmp_path / "scattered_2d.png"), min_bytes=20_000)
    assert len(fig.axes) == 3 + 3 * 2 + 2  # latent + 2 energy panels, 3 rows × 2 snapshots, 2 colour bars
    assert _colorbar_labels(fig) == ["field q₃", plotting.style._ERROR_LABEL]
    panels = [ax for ax in fig.axes[3:] if ax.get_label() != "<colorbar>"]
    for ax in panels:
        assert ax.get_xlim() == (-1.0, 1.0) and ax.get_ylim() == (0.0, 2.0)
        assert ax.get_aspect() == 1.0
    # panels are laid out row-major: [pred t12, pred t87, true t12, true t87, err t12, err t87]
    tri_col = panels[1].collections[0]
    faces = np.asarray(tri_col.get_array(), dtype=float)
    assert faces.ndim == 1 and faces.size > 200  # one colour per triangle of ~2N triangles
    assert np.isnan(faces).any() and np.isfinite(faces).any()
    assert not np.isnan(np.asarray(panels[0].collections[0].get_array(), dtype=float)).any()  # before: all finite
    texts = {i: [t.get_text() for t in ax.texts] for i, ax in enumerate(panels)}
    share = f"{100.0 * block.sum() / block.size:.0f}%"
    assert texts[0] == [] and texts[2] == [] and texts[3] == []  # true fields and the early prediction
    assert texts[1] == [f"non-finite\n{share} (grey)"] and texts[5] == [f"non-finite\n{share} (grey)"]
    titles = [ax.get_title() for ax in panels[:2]]
    assert "before horizon" in titles[0] and "after horizon" in titles[1]


def test_figure3_scattered_3d_random_points_middle_slab(data, tmp_path):
    """Random points of a 3-D body: the points of a slab around the middle of z, drawn as a 2-D body and
    labelled with the slab; too few points is a clear error."""
    rng = np.random.default_rng(4)
    pts = rng.uniform([0.0, 0.0, -0.5], [2.0, 1.0, 0.5], size=(400, 3))
    true = data["q_proj"] * (pts[:, 0] * pts[:, 1] + pts[:, 2])[None, :]
    fig = _figure3_on_points(data, pts, [[0, 2], [0, 1], [-0.5, 0.5]], true + 0.1, true, [12, 87])
    _assert_png(save_figure(fig, tmp_path / "scattered_3d.png"), min_bytes=20_000)
    assert len(fig.axes) == 3 + 3 * 2 + 2
    n_slab = int(np.count_nonzero(np.abs(pts[:, 2]) <= 1.0 / 16))
    labels = _colorbar_labels(fig)
    assert labels[0] == f"field q\n(slab X₃ ≈ 0 ± 0.062, {n_slab} points)" and labels[1] == plotting.style._ERROR_LABEL
    tri = fig.axes[3].collections[0]
    assert len(tri.get_paths()) == np.asarray(tri.get_array()).size > n_slab  # ~2·n_slab triangles
    assert fig.axes[3].get_xlim() == (0.0, 2.0) and fig.axes[3].get_ylim() == (0.0, 1.0)
    with pytest.raises(ValueError, match="at least 3 points"):
        _figure3_on_points(data, pts[:2], [[0, 2], [0, 1], [-0.5, 0.5]], true[:, :2], true[:, :2], [12])


def test_figure3_needs_grid_shape_or_points(data):
    args = (data["t"], data["q_pred"], data["q_proj"], data["energies"], None, BOUNDS,
            data["pred_fields"], data["true_fields"], [12], H)
    with pytest.raises(ValueError) as exc:
        figure3(*args)
    assert "grid_shape" in str(exc.value) and "points" in str(exc.value)
    pts = np.random.default_rng(0).uniform(-1, 1, (50, 2))
    with pytest.raises(ValueError, match=r"pred_fields must have shape \(T, N\) = \(100, 50\) with N = len\(points\)"):
        figure3(*args, points=pts)
    with pytest.raises(ValueError, match="points must have shape"):
        figure3(*args, points=np.zeros((256, 4)))
    with pytest.raises(ValueError, match="bounds"):
        figure3(*args[:5], [[0, 1]], *args[6:], points=np.zeros((256, 2)))
    collinear = np.stack([np.linspace(-1, 1, 256)] * 2, axis=1)
    with pytest.raises(ValueError, match="cannot be triangulated"):
        figure3(*args, points=collinear)
    # grid_shape wins over points (existing callers unchanged): the 16×16 grid's images, points ignored
    fig = figure3(*args[:4], G, *args[5:], points=pts)
    assert fig.axes[3].images[0].get_array().shape == (16, 16)


# --------------------------------------------------------------------------------------
# vector output, colour scales, energy panels, titles
# --------------------------------------------------------------------------------------


def _small_figure():
    fig = Figure(figsize=(3, 2))
    fig.add_subplot().plot([0, 1], [0, 1], label="q̃ predicted")
    return fig


def test_save_figure_writes_a_pdf_beside_the_png_atomically(tmp_path, monkeypatch):
    """A PNG (200 dpi) and a PDF of the same stem, each through a temporary name in the same folder and
    os.replace; the PNG's path is returned; pdf=False writes the PNG alone."""
    renamed = []
    replace = plotting.save.os.replace
    monkeypatch.setattr(plotting.save.os, "replace", lambda a, b: renamed.append((Path(a), Path(b))) or replace(a, b))
    out = save_figure(_small_figure(), tmp_path / "figs" / "f.png")
    assert out == tmp_path / "figs" / "f.png" and out.read_bytes()[:8] == PNG_MAGIC
    pdf = tmp_path / "figs" / "f.pdf"
    assert pdf.read_bytes()[:4] == PDF_MAGIC and b"%%EOF" in pdf.read_bytes()[-64:]
    assert [b for _, b in renamed] == [out, pdf]
    assert all(a.parent == b.parent and a.name.startswith(f".{b.name}.") and "tmp" in a.name for a, b in renamed)
    assert sorted(p.name for p in out.parent.iterdir()) == ["f.pdf", "f.png"]  # no temporary left
    from PIL import Image

    with Image.open(out) as im:
        assert im.size == (600, 400)  # 3 × 2 inches at 200 dpi
    save_figure(_small_figure(), tmp_path / "only.png", pdf=False)
    assert not (tmp_path / "only.pdf").exists()


def test_save_figure_leaves_no_temporary_when_the_pdf_fails(tmp_path, monkeypatch):
    replace = plotting.save.os.replace

    def fail_on_pdf(a, b):
        if str(b).endswith(".pdf"):
            raise OSError("disk full")
        replace(a, b)

    monkeypatch.setattr(plotting.save.os, "replace", fail_on_pdf)
    with pytest.raises(OSError, match="disk full"):
        save_figure(_small_figure(), tmp_path / "x.png")
    assert [p.name for p in tmp_path.iterdir() if "tmp" in p.name] == []


def _colorbar_of(fig, label):
    """The colour bar labelled `label` and the colour limits of what it shows."""
    cax = next(ax for ax in fig.axes if ax.get_label() == "<colorbar>" and ax.get_ylabel() == label)
    return cax._colorbar, cax._colorbar.mappable.get_clim()


def test_error_colour_scale_is_not_set_by_one_outlier(data):
    """One huge corner error: the error scale ends at a high percentile (below the outlier), the colour bar
    extends, and the light end of a sequential map is zero error."""
    pred = data["pred_fields"].copy()
    pred[:, 0] += 50.0  # one corner, every frame
    fig = figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], G, BOUNDS, pred,
                  data["true_fields"], [12, 87], H)
    err_panel = next(ax for ax in fig.axes if ax.get_ylabel().startswith("|pred − true|"))
    cbar, (lo, hi) = _colorbar_of(fig, plotting.style._ERROR_LABEL)
    assert err_panel.images[0].get_clim() == (lo, hi)  # every panel of the row on the colour bar's scale
    err = np.abs(pred - data["true_fields"])[[12, 87]]
    assert lo == 0.0 and hi < 0.1 * err.max() and hi >= np.percentile(err, 90)
    assert cbar.extend == "max" and cbar.ax.get_ylabel() == plotting.style._ERROR_LABEL
    cmap = err_panel.images[0].get_cmap()
    assert np.mean(cmap(0.0)[:3]) > 0.8 > np.mean(cmap(1.0)[:3])  # small errors light, large ones dark
    # the field scale: the true field's range; the saturated prediction gets an arrow, the truth none
    cbar_f, (flo, fhi) = _colorbar_of(fig, "field q")
    assert fhi == pytest.approx(np.abs(data["true_fields"][[12, 87]]).max(), rel=0.5) and fhi < 50
    assert cbar_f.extend in ("max", "both") and flo == -fhi
    # errors with no outlier: the whole range, no arrow
    fig = figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], G, BOUNDS, data["pred_fields"],
                  data["true_fields"], [12, 87], H)
    cbar, (_, hi) = _colorbar_of(fig, plotting.style._ERROR_LABEL)
    err = np.abs(data["pred_fields"] - data["true_fields"])[[12, 87]]
    assert hi <= err.max() and (cbar.extend == "neither" or hi >= np.percentile(err, 99) * 0.999)


@pytest.mark.parametrize("kind", ["1-D grid", "scattered 2-D"])
def test_error_colour_scale_is_robust_on_every_body(data, kind):
    rng = np.random.default_rng(1)
    if kind == "1-D grid":
        true = data["q_proj"] * np.sin(np.linspace(0, 3, 40))[None, :]
        pred = true + 0.01
        pred[50, 3] = 1e3  # one sample
        fig = figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], (40,), [[0, 1]], pred, true,
                      None, H)
    else:
        pts = rng.uniform(-1, 1, (150, 2))
        true = data["q_proj"] * pts[None, :, 0]
        pred = true + 0.01 * rng.standard_normal(true.shape)
        pred[:, 7] = 1e3
        fig = figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], None, BOUNDS, pred, true,
                      [12, 87], H, points=pts)
    cbar, (_, hi) = _colorbar_of(fig, plotting.style._ERROR_LABEL)
    assert hi < 1.0 and cbar.extend == "max"


def _energy_axes(fig):
    return fig.axes[1], fig.axes[2]  # total energy, kinetic / potential


def test_energy_panels_stay_readable_on_long_horizons():
    """5 s: kinetic/potential over the whole range; 20 s (many oscillations): total energy over the whole
    range, kinetic/potential in a window of a few periods around the training horizon, shaded on the other."""
    for t_end, windowed in ((5.0, False), (20.0, True)):
        t = 0.05 * np.arange(int(t_end / 0.05))
        w = np.sqrt(9.81)
        theta = 0.8 * np.cos(w * t)
        e = dict(kinetic_true=0.5 * (0.8 * w * np.sin(w * t)) ** 2, potential_true=0.5 * 9.81 * theta**2)
        e["kinetic_pred"], e["potential_pred"] = 1.01 * e["kinetic_true"], e["potential_true"]
        e["kinetic_pred"][-10:] = np.nan  # diverged at the end: a gap, not a failure
        fig = latent_and_energy_figure(t, theta, theta, e["kinetic_pred"], e["potential_pred"], e["kinetic_true"],
                                       e["potential_true"], H)
        ax_e, ax_x = _energy_axes(fig)
        total = ax_e.lines[0].get_ydata()
        np.testing.assert_allclose(total, e["kinetic_true"] + e["potential_true"])
        assert "total energy" in ax_e.get_ylabel() and "[J]" in ax_e.get_ylabel() and ax_x.get_xlabel() == "time t [s]"
        lo, hi = ax_x.get_xlim()
        if windowed:
            assert "window" in ax_x.get_title() and hi - lo < 0.5 * t_end and lo <= H <= hi
            assert ax_e.patches and ax_e.get_xlim()[1] >= t[-1] - 1e-9  # the window shaded, the total whole
        else:
            assert "window" not in ax_x.get_title() and lo == t[0] and hi == pytest.approx(t[-1])
        assert all(ax.get_legend() is not None for ax in fig.axes[:3])


def test_figure3_title_is_what_is_passed(data):
    title = "test trajectory 0 · RK4 · dt = 0.05 s"
    fig = figure3(data["t"], data["q_pred"], data["q_proj"], data["energies"], G, BOUNDS, data["pred_fields"],
                  data["true_fields"], [12], H, title=title)
    assert fig._suptitle.get_text() == title


def test_evaluation_figures_name_the_integrator_and_time_step(data, tmp_path, monkeypatch):
    """save_evaluation_figures titles each Figure 3 with the trajectory, the integrator (when given) and dt (the
    times' spacing unless given), and writes the PNG and PDF."""
    from types import SimpleNamespace

    from lnf.evaluation import RolloutEvaluation
    from lnf.evaluation_pipeline import save_evaluation_figures

    n = 2
    result = RolloutEvaluation(
        metrics={}, times=data["t"], q_pred=np.stack([data["q_pred"]] * n), q_ref=np.stack([data["q_proj"]] * n),
        pred_fields=np.stack([data["pred_fields"]] * n)[..., None],
        true_fields=np.stack([data["true_fields"]] * n)[..., None],
        energies={k: np.stack([v] * n) for k, v in data["energies"].items()})
    scene = SimpleNamespace(field_dim=1, bounds=[list(b) for b in BOUNDS])
    titles = []
    monkeypatch.setattr(plotting, "save_figure", lambda fig, path: titles.append(fig._suptitle.get_text()) or path)
    for integrator, dt, words in [("rk4", None, "RK4 · dt = 0.05 s"),
                                  ({"name": "implicit_midpoint", "order": 4, "substeps": 2}, 0.1,
                                   "implicit midpoint (order 4) · dt = 0.1 s in 2 substeps"),
                                  (None, None, "dt = 0.05 s")]:
        titles.clear()
        paths = save_evaluation_figures(result, scene, G, H, tmp_path, "test", 2, integrator=integrator, dt=dt)
        assert paths == [tmp_path / "test_trajectory0.png", tmp_path / "test_trajectory1.png"]
        assert titles == [f"test trajectory {i} · {words}" for i in range(2)]
    monkeypatch.undo()
    monkeypatch.setenv("LNF_FIGURE_PDF", "1")  # undo() took the vector_figures fixture's setting back too
    out = save_evaluation_figures(result, scene, G, H, tmp_path / "real", "test", 1, integrator="rk4")
    assert out[0].read_bytes()[:8] == PNG_MAGIC and out[0].with_suffix(".pdf").read_bytes()[:4] == PDF_MAGIC


def test_the_environment_can_turn_the_pdf_off(tmp_path, monkeypatch):
    """LNF_FIGURE_PDF=0 writes the PNG alone; an explicit pdf=True still writes both."""
    fig = Figure()
    fig.add_subplot().plot([0, 1], [0, 1])
    monkeypatch.setenv("LNF_FIGURE_PDF", "0")
    save_figure(fig, tmp_path / "a.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]
    save_figure(fig, tmp_path / "b.png", pdf=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.pdf", "b.png"]


def test_figure3_leaves_the_cut_out_of_an_l_shaped_body_empty(data):
    """Nodes of an L-shaped membrane (the square [0, 1]² less its upper-right quarter): the triangles drawn cover the
    L, and none bridges its cut-out, which the convex hull's triangulation used to fill."""
    g = (np.arange(20) + 0.5) / 20
    X, Y = np.meshgrid(g, g, indexing="ij")
    pts = np.c_[X.ravel(), Y.ravel()]
    pts = pts[~((pts[:, 0] > 0.5) & (pts[:, 1] > 0.5))]
    u = np.sin(np.pi * pts[:, 0]) * np.sin(np.pi * pts[:, 1])
    true = data["q_proj"] * u[None, :]
    fig = _figure3_on_points(data, pts, [[0.0, 1.0], [0.0, 1.0]], 1.05 * true, true, [12, 87])
    panels = [ax for ax in fig.axes[3:] if ax.get_label() != "<colorbar>"]
    drawn = []
    for path in panels[0].collections[0].get_paths():
        corners = np.asarray(path.vertices)[:3]
        drawn.append(corners.mean(axis=0))
    drawn = np.asarray(drawn)
    assert len(drawn) > 500  # the L's own triangles (2 per cell of its 300 points) are all drawn
    deep = (drawn[:, 0] > 0.6) & (drawn[:, 1] > 0.6)  # centroids in the cut-out, away from its re-entrant corner
    assert not deep.any(), drawn[deep]
    assert np.isfinite(np.asarray(panels[0].collections[0].get_array(), dtype=float)).all()
    _close(fig)
