"""SnapshotDataModule: lazy HDF5 snapshots equal the in-memory ones; noise, workers, damaged files."""
from __future__ import annotations

import pickle

import h5py
import numpy as np
import pytest
import torch

from lnf.dataset import DatasetError, load_split
from lnf.training.datamodule import SnapshotDataModule

GEN = dict(n_train=3, n_val=1, n_test=2, n_times=12, dt=0.05, train_times=6, fine_resolution=8,
           coarse_resolution=8, observed_fraction=0.25, seed=0)


def _module(tmp_path, **kwargs) -> SnapshotDataModule:
    dm = SnapshotDataModule({"_target_": "lnf.scenes.LiftedPendulum"}, data_dir=str(tmp_path), batch_size=4,
                            **GEN, **kwargs)
    dm.prepare_data()
    return dm


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return _module(tmp_path_factory.mktemp("data")).path.parent


def _all(loader):
    batches = list(loader)
    return [torch.cat([getattr(b, key) for b in batches]) for key in ("points", "values", "velocities")]


def test_batches_are_typed_and_carry_only_the_targets_asked_for(data_dir):
    from lnf.training.batch import SnapshotBatch

    batch = next(iter(_module(data_dir).train_dataloader()))
    assert isinstance(batch, SnapshotBatch) and batch.potential is None and batch.gradients is None
    assert batch.values.shape[0] == len(batch) == batch.points.shape[0]
    dm = _module(data_dir)
    dm.potential_targets = True
    batch = next(iter(dm.train_dataloader()))
    assert batch.potential.shape == (len(batch),) and batch.gradients is None


def test_snapshots_are_the_masked_coarse_observations(data_dir):
    dm = _module(data_dir)
    ds = dm.snapshots("train")
    assert ds._arrays is None and len(ds) == 3 * 6
    split = load_split(dm.path, "train")
    idx = np.flatnonzero(split.masks[1])
    item = ds[1 * 6 + 4]
    points, values, velocities = item["points"], item["values"], item["velocities"]
    np.testing.assert_array_equal(points.numpy(), split.coarse_points[idx])
    np.testing.assert_array_equal(values.numpy(), split.coarse_fields[1, 4, idx])
    np.testing.assert_array_equal(velocities.numpy(), split.coarse_velocities[1, 4, idx])


@pytest.mark.parametrize("noise", [0.0, 0.1])
def test_lazy_equals_in_memory_and_workers_equal_main_process(data_dir, noise):
    lazy = _module(data_dir, noise=noise).train_dataloader()
    memory = _module(data_dir, noise=noise, in_memory=True).train_dataloader()
    workers = _module(data_dir, noise=noise, num_workers=2).train_dataloader()
    a, b, c = _all(lazy), _all(memory), _all(workers)
    for x, y, z in zip(a, b, c):
        assert torch.equal(x, y) and torch.equal(x, z)


def test_noise_has_the_stated_size_and_only_on_training(data_dir):
    clean, noisy = _module(data_dir), _module(data_dir, noise=0.1)
    _, v0, w0 = clean.observations("train")
    _, v1, w1 = noisy.observations("train")
    assert np.std(v1 - v0) == pytest.approx(0.1 * np.sqrt(np.mean(v0.astype(np.float64) ** 2)), rel=0.1)
    assert np.std(w1 - w0) == pytest.approx(0.1 * np.sqrt(np.mean(w0.astype(np.float64) ** 2)), rel=0.1)
    assert all(np.array_equal(x, y) for x, y in zip(clean.observations("val"), noisy.observations("val")))
    # the stacked observations are the items of the dataset
    ds = noisy.snapshots("train")
    np.testing.assert_array_equal(v1[2, 3], ds[2 * 6 + 3]["values"].numpy())


def test_lazy_dataset_pickles_without_its_file_handle(data_dir):
    ds = _module(data_dir).snapshots("train")
    ds[0]
    assert ds._file is not None
    copy = pickle.loads(pickle.dumps(ds))
    assert copy._file is None and torch.equal(copy[5]["values"], ds[5]["values"])
    ds.close()


def test_damaged_snapshot_names_file_key_and_trajectory(tmp_path):
    dm = _module(tmp_path)
    with h5py.File(dm.path, "r+") as f:
        f["train/coarse_fields"][2, 1] = np.nan
    ds = dm.snapshots("train")
    ds[2 * 6]  # an intact snapshot reads fine
    with pytest.raises(DatasetError, match=r"/train/coarse_fields .*trajectory 2"):
        ds[2 * 6 + 1]


def test_bad_settings(tmp_path):
    with pytest.raises(ValueError, match="data.num_workers"):
        SnapshotDataModule({"_target_": "lnf.scenes.LiftedPendulum"}, data_dir=str(tmp_path), num_workers=-1, **GEN)


def test_potential_targets_are_the_full_order_potential_of_each_snapshot(data_dir):
    dm = _module(data_dir)
    dm.potential_targets = True
    ds = dm.snapshots("train")
    split = load_split(dm.path, "train")
    potential = ds[2 * 6 + 3]["potential"]
    _, expected = dm.scene.true_energy_parts(split.states[2, 3])
    assert potential.shape == () and potential.item() == pytest.approx(float(expected), rel=1e-6)
    assert set(_module(data_dir).snapshots("train")[0]) == {"points", "values", "velocities"}  # off by default


def test_gradient_targets_are_the_scenes_field_gradients_at_the_observed_points(data_dir):
    """The pendulum's q = θ u(X): each item's ∇_X q is θ ∇u at its own observed points (θ read off its values)."""
    from lnf.scenes.pendulum import legendre_mode, legendre_mode_gradient

    dm = _module(data_dir)
    dm.gradient_targets = True
    item = dm.snapshots("train")[3]
    points = item["points"].double().numpy()
    u, grad_u = legendre_mode(points, (3, 4)), legendre_mode_gradient(points, (3, 4))
    theta = float(np.dot(item["values"][:, 0].double().numpy(), u) / np.dot(u, u))
    assert item["gradients"].shape == (len(points), 1, 2)
    np.testing.assert_allclose(item["gradients"][:, 0].double().numpy(), theta * grad_u, rtol=1e-4, atol=1e-4)


def test_acceleration_targets_are_fourth_order_differences_of_the_observed_velocities(data_dir):
    """Items carry the observed acceleration field (−u̇_{k+2} + 8u̇_{k+1} − 8u̇_{k−1} + u̇_{k−2}) / (12 dt) inside the
    training window, and none within two samples of its ends (nothing after the training horizon is read)."""
    dm = _module(data_dir)
    dm.acceleration_targets = True
    ds = dm.snapshots("train")
    split = load_split(dm.path, "train")
    idx = np.flatnonzero(split.masks[2])
    u = split.coarse_velocities[2][:, idx]
    item = ds[2 * 6 + 3]
    expected = (-u[5] + 8 * u[4] - 8 * u[2] + u[1]) / (12 * 0.05)
    assert bool(item["acceleration_valid"])
    np.testing.assert_allclose(item["accelerations"].numpy(), expected, rtol=1e-5, atol=1e-6)
    for k in (0, 1, 4, 5):  # train_times = 6: k + 2 must stay below it
        edge = ds[2 * 6 + k]
        assert not bool(edge["acceleration_valid"]) and edge["accelerations"].shape == item["accelerations"].shape
    batch = next(iter(dm.train_dataloader()))
    assert batch.accelerations.shape == batch.values.shape and batch.acceleration_valid.dtype == torch.bool


def test_with_noise_the_acceleration_is_that_of_the_neighbours_noisy_velocities(data_dir):
    """The stencil reads each neighbour's velocities with the noise that neighbour's own item carries."""
    dm = _module(data_dir, noise=0.1)
    dm.acceleration_targets = True
    ds = dm.snapshots("train")
    u = {j: ds[1 * 6 + 3 + j]["velocities"].numpy() for j in (-2, -1, 1, 2)}
    expected = (-u[2] + 8 * u[1] - 8 * u[-1] + u[-2]) / (12 * 0.05)
    np.testing.assert_allclose(ds[1 * 6 + 3]["accelerations"].numpy(), expected, rtol=1e-5, atol=1e-5)


def test_the_handle_without_loaders_reads_the_same_file_and_imports_no_lightning(data_dir, tmp_path):
    """lnf.evaluate, the closure fit and Operator Inference's study read data through SnapshotData, which (with
    lnf.evaluate itself) imports no Lightning: 3–6 s less at every start of an evaluation or a study."""
    import subprocess
    import sys

    from lnf.dataset.snapshots import SnapshotData

    plain = SnapshotData.from_settings({"_target_": "lnf.training.datamodule.SnapshotDataModule",
                                        "data_dir": str(data_dir), **GEN}, {"_target_": "lnf.scenes.LiftedPendulum"})
    plain.prepare_data()
    module = _module(data_dir)
    assert plain.path == module.path and plain.checksum == module.checksum
    for got, want in zip(plain.observations("train"), module.observations("train")):
        np.testing.assert_array_equal(got, want)
    code = ("import sys, lnf.evaluate, lnf.dataset.snapshots, experiments.operator_inference; "
            "loaded = sorted(m for m in sys.modules if m.split('.')[0] == 'lightning'); "
            "assert not loaded, loaded")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
