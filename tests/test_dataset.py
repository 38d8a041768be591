"""Dataset generation, reuse and validation (lnf.dataset) on a tiny lifted-pendulum dataset."""
from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from lnf.dataset import (FORMAT_VERSION, SPLITS, DatasetConfig, DatasetError, ensure_dataset, generate_dataset,
                         generation_attributes, load_split)
from lnf.quadrature import gauss_legendre_rule
from lnf.scenes import LiftedPendulum
from tiny_dataset import CFG, fresh_file, scene, shared_file  # noqa: F401 (fixtures)


def no_temp_files(directory: Path) -> bool:
    return not any(".tmp-" in p.name for p in directory.iterdir())


# -- contents --------------------------------------------------------------------------------------------
def test_layout_and_shapes(shared_file, scene):
    with h5py.File(shared_file, "r") as f:
        assert f.attrs["format_version"] == FORMAT_VERSION and f.attrs["scene_name"] == "pendulum"
        np.testing.assert_allclose(f["times"][...], 0.05 * np.arange(12), rtol=0, atol=1e-15)
        assert f["grids/fine"].shape == (64, 2) and f["grids/coarse"].shape == (64, 2)
        assert f["grids/fine"].dtype == np.float64  # points exactly (a mesh's nodes rounded to float32 can leave it)
        for split, n in zip(SPLITS, (3, 1, 2)):
            assert f[f"{split}/states"].shape == (n, 12, 2) and f[f"{split}/states"].dtype == np.float64
            assert f[f"{split}/fields"].shape == (n, 12, 64, 1) and f[f"{split}/fields"].dtype == np.float32
            assert f[f"{split}/masks"].shape == (n, 64) and f[f"{split}/masks"].dtype == bool
    split = load_split(shared_file, "test", scene=scene, cfg=CFG)
    assert len(split) == 2 and split.train_times == 6
    assert split.attrs["generation"]["n_train"] == 3 and split.attrs["scene"]["gravity"] == 9.81


def test_fields_are_mode_times_state(shared_file, scene):
    s = load_split(shared_file, "test")
    u = scene.mode(s.fine_points.astype(np.float64))  # (Nf,)
    np.testing.assert_allclose(s.fields[..., 0], s.states[..., 0, None] * u, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(s.velocities[..., 0], s.states[..., 1, None] * u, rtol=1e-6, atol=1e-6)
    uc = scene.mode(s.coarse_points.astype(np.float64))
    np.testing.assert_allclose(s.coarse_fields[..., 0], s.states[..., 0, None] * uc, rtol=1e-6, atol=1e-6)


def test_projection_on_mode_recovers_theta(shared_file, scene):
    """⟨q, u⟩ = θ checks ‖u‖_{L²} = 1 (P₃P₄ is degree ≤ 7 per axis: 8-point Gauss–Legendre is exact)."""
    s = load_split(shared_file, "test")
    quad = gauss_legendre_rule(8, scene.bounds)  # float32 tensors: to ~1e-6
    x, w = np.polynomial.legendre.leggauss(8)  # the same rule in float64, for the 1e-10 check
    pts = np.stack([a.ravel() for a in np.meshgrid(x, x, indexing="ij")], -1)
    wts = np.outer(w, w).ravel()
    np.testing.assert_allclose(pts, quad.points.numpy(), atol=1e-6)
    q, _ = scene.fields(s.states, pts)  # (n, T, N, 1)
    theta = np.einsum("ntj,j,j->nt", q[..., 0], wts, scene.mode(pts))
    np.testing.assert_allclose(theta, s.states[..., 0], rtol=0, atol=1e-10)
    q32, _ = scene.fields(s.states, quad.points.double().numpy())
    theta32 = np.einsum("ntj,j,j->nt", q32[..., 0], quad.weights.double().numpy(),
                        scene.mode(quad.points.double().numpy()))
    np.testing.assert_allclose(theta32, s.states[..., 0], rtol=0, atol=1e-5)


def test_states_solve_the_ode(shared_file, scene):
    for name in SPLITS:
        s = load_split(shared_file, name)
        np.testing.assert_allclose(s.energy, scene.true_energy(s.states), rtol=1e-15)
        scale = np.maximum(np.abs(s.energy[:, :1]), 1e-3 * scene.energy_scale)
        assert np.max(np.abs(s.energy - s.energy[:, :1]) / scale) < 1e-8
        # the stored times are the ones simulated: re-solving from the first state reproduces the rest
        np.testing.assert_allclose(scene.simulate(s.states[:, 0], s.times), s.states, rtol=1e-8, atol=1e-9)


def test_masks_fixed_distinct_and_quarter(shared_file):
    a, b = load_split(shared_file, "train"), load_split(shared_file, "train")
    np.testing.assert_array_equal(a.masks, b.masks)
    assert (a.masks.sum(axis=1) == 16).all()  # 25 % of 8×8
    assert len({m.tobytes() for m in a.masks}) == len(a.masks)
    points, values = a.observed(max_time=6)
    assert points.shape == (3, 16, 2) and values.shape == (3, 6, 16, 1)
    for i in range(3):
        np.testing.assert_array_equal(points[i], a.coarse_points[a.masks[i]])
        np.testing.assert_array_equal(values[i], a.coarse_fields[i, :6][:, a.masks[i]])
    assert a.observed()[1].shape == (3, 12, 16, 1)
    with pytest.raises(DatasetError, match="max_time"):
        a.observed(13)


def test_splits_are_disjoint_trajectories(shared_file):
    initial = [tuple(x) for name in SPLITS for x in load_split(shared_file, name).states[:, 0]]
    assert len(initial) == 6 and len(set(initial)) == 6


def test_generation_is_deterministic(tmp_path, scene, shared_file):
    other = generate_dataset(scene, CFG, tmp_path / "again.h5")
    a, b = load_split(shared_file, "val"), load_split(other, "val")
    np.testing.assert_array_equal(a.states, b.states)
    np.testing.assert_array_equal(a.masks, b.masks)


def test_vertex_observation_grid_reaches_the_boundary(tmp_path, scene, shared_file):
    path = generate_dataset(scene, replace(CFG, coarse_grid="vertices"), tmp_path / "vertices.h5")
    with h5py.File(path, "r") as f, h5py.File(shared_file, "r") as g:
        coarse, centres = f["grids/coarse"][...], g["grids/coarse"][...]
        assert coarse.shape == centres.shape == (64, 2)
        assert coarse.min() == -1.0 and coarse.max() == 1.0 and -1.0 < centres.min() and centres.max() < 1.0
        np.testing.assert_array_equal(f["grids/fine"][...], g["grids/fine"][...])  # the evaluation grid stays
        assert f.attrs["lnf_generation"] != g.attrs["lnf_generation"]
    split = load_split(path, "test", scene=scene, cfg=replace(CFG, coarse_grid="vertices"))
    q, _ = scene.fields(split.states[0], split.coarse_points.astype(np.float64))
    np.testing.assert_allclose(split.coarse_fields[0], q, rtol=0, atol=1e-6)
    with pytest.raises(DatasetError, match="generation.coarse_grid: file .*vertices"):
        ensure_dataset(scene, CFG, path, on_mismatch="error")


def test_vertex_grid_of_a_scene_with_its_own_points_is_an_error(tmp_path):
    class OwnPoints(LiftedPendulum):
        def observation_points(self, resolution):
            return super().observation_points(resolution)

    with pytest.raises(DatasetError, match="gives its own observation points.*data.coarse_grid=centres"):
        generate_dataset(OwnPoints(), replace(CFG, coarse_grid="vertices"), tmp_path / "own.h5")
    assert not list(tmp_path.iterdir())


def test_default_observation_grid_is_not_recorded(scene):
    """Files written before data.coarse_grid existed keep matching the default configuration."""
    assert "coarse_grid" not in generation_attributes(scene, CFG)["generation"]
    assert generation_attributes(scene, replace(CFG, coarse_grid="vertices"))["generation"]["coarse_grid"] == "vertices"


# -- reuse and regeneration ------------------------------------------------------------------------------
def test_same_config_reuses_file(fresh_file, scene):
    with h5py.File(fresh_file, "a") as f:
        f.attrs["marker"] = 7
    mtime = fresh_file.stat().st_mtime_ns
    assert ensure_dataset(scene, CFG, fresh_file, on_mismatch="error") == fresh_file
    assert ensure_dataset(scene, CFG, fresh_file) == fresh_file
    assert fresh_file.stat().st_mtime_ns == mtime
    with h5py.File(fresh_file, "r") as f:
        assert f.attrs["marker"] == 7


def test_different_config_error_mode(fresh_file, scene):
    with pytest.raises(DatasetError) as err:
        ensure_dataset(scene, replace(CFG, n_train=4), fresh_file, on_mismatch="error")
    msg = str(err.value)
    assert fresh_file.name in msg and "generation.n_train: file 3, config 4" in msg
    with pytest.raises(DatasetError, match="scene.gravity: file 9.81, config 9.0"):
        ensure_dataset(LiftedPendulum(gravity=9.0), CFG, fresh_file, on_mismatch="error")
    with pytest.raises(DatasetError, match="generation.n_train: file 3, config 4"):
        load_split(fresh_file, "test", cfg=replace(CFG, n_train=4))


def test_different_config_regenerates(fresh_file, scene, caplog):
    new = replace(CFG, n_train=4, seed=1)
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
        ensure_dataset(scene, new, fresh_file)
    assert "generation.n_train: file 3, config 4" in caplog.text and "generation.seed" in caplog.text
    s = load_split(fresh_file, "train", scene=scene, cfg=new)
    assert s.states.shape[0] == 4 and s.attrs["generation"]["seed"] == 1
    assert no_temp_files(fresh_file.parent)


def test_missing_file_is_generated(tmp_path, scene):
    path = ensure_dataset(scene, CFG, tmp_path / "sub" / "dir" / "d.h5")
    assert path.is_file() and load_split(path, "val").states.shape == (1, 12, 2)


def test_bad_on_mismatch(fresh_file, scene):
    with pytest.raises(DatasetError, match="data.on_mismatch"):
        ensure_dataset(scene, CFG, fresh_file, on_mismatch="ignore")


# -- bad input -------------------------------------------------------------------------------------------
def test_bad_config_names_key():
    with pytest.raises(DatasetError, match=r"data\.n_train must be an integer ≥ 1, got 0"):
        DatasetConfig(n_train=0)
    with pytest.raises(DatasetError, match=r"data\.train_times"):
        DatasetConfig(n_times=10, train_times=11)
    with pytest.raises(DatasetError, match=r"data\.observed_fraction"):
        DatasetConfig(observed_fraction=0.0)
    with pytest.raises(DatasetError, match=r"data\.dt"):
        DatasetConfig(dt=-0.1)
    with pytest.raises(DatasetError, match=r"data\.coarse_grid must be one of centres, vertices, got 'edges'"):
        DatasetConfig(coarse_grid="edges")
    with pytest.raises(DatasetError, match=r"data\.coarse_grid=vertices needs data\.coarse_resolution ≥ 2"):
        DatasetConfig(coarse_grid="vertices", coarse_resolution=1)
    with pytest.raises(DatasetError, match=r"data\.bogus"):
        DatasetConfig.from_mapping({"bogus": 1})
    assert DatasetConfig(dt=1).dt == 1.0 and isinstance(DatasetConfig(dt=1).dt, float)


def test_missing_file(tmp_path):
    with pytest.raises(DatasetError, match=r"nope\.h5.*not found"):
        load_split(tmp_path / "nope.h5", "test")
    assert list(tmp_path.iterdir()) == []


def test_unknown_split(shared_file):
    with pytest.raises(DatasetError, match="split"):
        load_split(shared_file, "training")


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_corrupt_file(tmp_path, fresh_file, scene, damage, caplog):
    if damage == "garbage":
        fresh_file.write_bytes(b"this is not an HDF5 file\n" * 10)
    else:
        data = fresh_file.read_bytes()
        fresh_file.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=r"pendulum\.h5.*corrupt or not an HDF5"):
        load_split(fresh_file, "test")
    with pytest.raises(DatasetError, match=r"pendulum\.h5.*corrupt.*on_mismatch=regenerate"):
        ensure_dataset(scene, CFG, fresh_file, on_mismatch="error")
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
        ensure_dataset(scene, CFG, fresh_file)
    assert "corrupt" in caplog.text
    assert load_split(fresh_file, "test", scene=scene, cfg=CFG).fields.shape == (2, 12, 64, 1)
    assert no_temp_files(tmp_path)


def test_wrong_format_version(fresh_file, scene):
    with h5py.File(fresh_file, "a") as f:
        f.attrs["format_version"] = 0
    with pytest.raises(DatasetError, match=rf"pendulum\.h5.*format_version 0, this lnf reads {FORMAT_VERSION}"):
        load_split(fresh_file, "test")
    with pytest.raises(DatasetError, match=rf"format_version: file 0, config {FORMAT_VERSION}"):
        ensure_dataset(scene, CFG, fresh_file, on_mismatch="error")
    with h5py.File(fresh_file, "a") as f:
        del f.attrs["format_version"]
    with pytest.raises(DatasetError, match=r"pendulum\.h5.*format_version is missing"):
        load_split(fresh_file, "test")


@pytest.mark.parametrize("value, kind", [(np.nan, "1 NaN"), (np.inf, "1 inf")])
def test_non_finite_values(fresh_file, value, kind):
    with h5py.File(fresh_file, "a") as f:
        f["test/fields"][1, 3, 5, 0] = value
    with pytest.raises(DatasetError, match=rf"pendulum\.h5.*/test/fields contains 1 non-finite.*{kind}"):
        load_split(fresh_file, "test")
    load_split(fresh_file, "train")  # other splits stay loadable


def test_missing_key_and_bad_shapes(fresh_file):
    with h5py.File(fresh_file, "a") as f:
        del f["val/energy"]
        data = f["test/velocities"][:, :5]
        del f["test/velocities"]
        f["test/velocities"] = data
    with pytest.raises(DatasetError, match=r"pendulum\.h5.*/val/energy is missing"):
        load_split(fresh_file, "val")
    with pytest.raises(DatasetError, match=r"pendulum\.h5.*/test/velocities has shape \(2, 5, 64, 1\)"):
        load_split(fresh_file, "test")


def test_uneven_masks(fresh_file):
    with h5py.File(fresh_file, "a") as f:
        f["train/masks"][0, :] = True
    with pytest.raises(DatasetError, match=r"pendulum\.h5.*/train/masks.*same number"):
        load_split(fresh_file, "train")


def test_failed_generation_leaves_nothing(tmp_path, scene, monkeypatch):
    def boom(*args, **kwargs):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(scene, "simulate", boom)
    target = tmp_path / "d.h5"
    with pytest.raises(RuntimeError, match="solver exploded"):
        ensure_dataset(scene, CFG, target)
    assert list(tmp_path.iterdir()) == []


def test_failed_regeneration_keeps_old_file(fresh_file, scene, monkeypatch):
    monkeypatch.setattr(scene, "simulate", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("boom")))
    with pytest.raises(RuntimeError):
        ensure_dataset(scene, replace(CFG, seed=5), fresh_file)
    assert no_temp_files(fresh_file.parent)
    assert load_split(fresh_file, "test", cfg=CFG).attrs["generation"]["seed"] == 0


def test_generation_attributes_are_json(scene):
    attrs = generation_attributes(scene, CFG)
    assert attrs["format_version"] == FORMAT_VERSION
    assert attrs["scene"]["_target_"] == "lnf.scenes.pendulum.LiftedPendulum"
    assert attrs["generation"]["coarse_resolution"] == 8


def test_killed_generation_leaves_no_partial_file(tmp_path):
    """SIGKILL in the middle of writing: no file at the target; the next run removes the temporary."""
    import os
    import signal
    import subprocess
    import sys
    import time

    target = tmp_path / "big.h5"
    code = ("import sys; from lnf.dataset import DatasetConfig, generate_dataset; from lnf.scenes import LiftedPendulum; "
            "generate_dataset(LiftedPendulum(), DatasetConfig(n_train=400, n_times=100, fine_resolution=64), sys.argv[1])")
    proc = subprocess.Popen([sys.executable, "-c", code, str(target)])
    deadline = time.monotonic() + 120
    while not any(".tmp-" in p.name for p in tmp_path.iterdir()):
        assert proc.poll() is None and time.monotonic() < deadline, "the writer ended before it could be killed"
        time.sleep(0.05)
    time.sleep(0.5)  # well inside the writing of the file
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL
    assert not target.exists() and not no_temp_files(tmp_path)
    path = ensure_dataset(LiftedPendulum(), CFG, target)
    assert no_temp_files(tmp_path) and load_split(path, "test", cfg=CFG).states.shape[0] == 2
