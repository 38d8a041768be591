"""Your own trajectories (lnf.trajectories, lnf.mesh_io): arrays from any simulator become an lnf dataset that
training and evaluation read, verified and never regenerated; scattered points train, evaluate and draw."""
import hashlib
import json

import h5py
import numpy as np
import pytest
import torch

from helpers import TINY, compose_config
from lnf.dataset import DatasetConfig, DatasetError, ensure_dataset, load_split, stored_generation, verify_dataset
from lnf.dataset.generate import _write_array
from lnf.scenes import LiftedPendulum
from lnf.trajectories import Trajectories, write_dataset


def _string(n: int, T: int = 12, N: int = 9, dt: float = 0.1, seed: int = 0) -> Trajectories:
    """Standing waves q = a cos(πt) sin(πX) on N scattered (unsorted) points of [0, 1]."""
    x = np.random.default_rng(42).permutation(np.linspace(0.05, 0.95, N))  # the same points in every split
    rng = np.random.default_rng(seed)
    t = dt * np.arange(T)
    a = rng.uniform(0.5, 1.0, (n, 1, 1))
    q = a * np.cos(np.pi * t)[None, :, None] * np.sin(np.pi * x)[None, None, :]
    v = -np.pi * a * np.sin(np.pi * t)[None, :, None] * np.sin(np.pi * x)[None, None, :]
    return Trajectories(points=x[:, None], times=t, fields=q, velocities=v, weights=np.full(N, 1.0 / N))


def _splits(**kw):
    return _string(3, **kw), _string(1, seed=1, **kw), _string(2, seed=2, **kw)


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _as_before_manifests(f):
    """Make the open file `f` one of an lnf that wrote no lnf_manifest (its attribute checksums without it)."""
    del f.attrs["lnf_manifest"]
    digests = json.loads(f.attrs["lnf_attributes_checksum"])
    del digests["lnf_manifest"]
    f.attrs["lnf_attributes_checksum"] = json.dumps(digests)


@pytest.mark.parametrize("change, message", [
    (dict(times=0.1 * np.arange(12) ** 1.01), "uniformly spaced"),
    (dict(times=0.1 * np.arange(12) + 1.0), "must start at 0"),
    (dict(fields=np.zeros((2, 12, 8, 1))), "fields: expected shape (n, T, N, A) = (n, 12, 9, A)"),
    (dict(fields=np.full((2, 12, 9, 1), np.nan)), "NaN or inf"),
    (dict(weights=-np.ones(9)), "positive quadrature weights"),
    (dict(kinetic=np.zeros((2, 12))), "give both energy parts or neither"),
    (dict(states=np.zeros((3, 12, 2))), "states: expected shape (n, T, S) = (2, 12, S)"),
    (dict(fields=np.ones((2, 12, 9)) * (1 + 1j)), "fields: got a complex array (dtype complex128); lnf expects real"),
    (dict(points=np.linspace(0, 1, 9) + 0j), "points: got a complex array (dtype complex128)"),
])
def test_trajectories_refuse_bad_arrays_by_name(change, message):
    good = dict(points=np.linspace(0, 1, 9), times=0.1 * np.arange(12), fields=np.zeros((2, 12, 9)))
    with pytest.raises(DatasetError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Trajectories(**{**good, **change})


def test_velocities_default_to_second_order_central_differences():
    t = 0.1 * np.arange(11)
    q = (t ** 2)[None, :, None] * np.ones(4)  # q = t² at every point: q̇ = 2t exactly, ends included
    tr = Trajectories(points=np.linspace(0, 1, 4), times=t, fields=q)
    assert not tr.velocities_given
    np.testing.assert_allclose(tr.velocities[0, :, :, 0], np.repeat(2 * t[:, None], 4, 1), atol=1e-5)


def test_write_dataset_round_trip_links_observations_and_is_verified(tmp_path):
    train, val, test = _splits()
    path = write_dataset(tmp_path / "mine.h5", train, val, test, train_times=6, observed_fraction=0.5, seed=3)
    split = load_split(path, "test")
    assert split.from_arrays and split.train_times == 6 and split.states.shape == (2, 12, 0)
    np.testing.assert_allclose(split.fields, test.fields, rtol=1e-6)
    np.testing.assert_allclose(split.fine_points, test.points, rtol=1e-6)
    np.testing.assert_allclose(split.weights, test.weights)
    assert split.energy is None and split.energy_parts() is None  # none given: no energies
    assert (split.masks.sum(1) == round(0.5 * 9)).all()
    with h5py.File(path) as f:  # the observations are the same datasets, linked, not copied
        assert f["grids/coarse"] == f["grids/fine"] and f["test/coarse_fields"] == f["test/fields"]
        generation = json.loads(f.attrs["lnf_generation"])
    assert generation["source"] == "arrays" and generation["velocities"] == "given"
    assert verify_dataset(path) == path

    before = _digest(path)  # generation never touches a user's file: a scene that does not fit is refused
    with pytest.raises(DatasetError, match="the points have 1 coordinates .*, but scene 'pendulum' has a 2-D body"):
        ensure_dataset(LiftedPendulum(), DatasetConfig(), path)
    assert _digest(path) == before
    with pytest.raises(DatasetError, match="a file exists there; pass overwrite=True"):
        write_dataset(path, train, val, test)
    assert _digest(path) == before


def test_a_damaged_file_from_arrays_is_refused_not_regenerated(tmp_path):
    path = write_dataset(tmp_path / "mine.h5", *_splits())
    with h5py.File(path, "r+") as f:
        f["train/fields"][0, 0, 0, 0] += 1.0
    before = _digest(path)
    with pytest.raises(DatasetError, match=r"/train/fields does not match its lnf_checksum.*cannot be regenerated"):
        verify_dataset(path)
    with pytest.raises(DatasetError, match=r"/train/fields does not match its lnf_checksum.*cannot be regenerated"):
        load_split(path, "train")
    assert _digest(path) == before


def test_splits_must_share_points_and_times_and_scene_must_fit(tmp_path):
    train, val, test = _splits()
    other = _string(1, N=9, seed=5)
    other.points = other.points + 0.01
    with pytest.raises(DatasetError, match="val: its points differ"):
        write_dataset(tmp_path / "a.h5", train, other, test)
    with pytest.raises(DatasetError, match="points have 1 coordinates, but scene 'pendulum' has a 2-D body"):
        write_dataset(tmp_path / "a.h5", train, val, test, scene=LiftedPendulum())
    assert not (tmp_path / "a.h5").exists()


def _on(points: np.ndarray, n: int, seed: int) -> Trajectories:
    """n random trajectories (T = 4) on `points`."""
    return Trajectories(points=points, times=0.1 * np.arange(4),
                        fields=np.random.default_rng(seed).normal(size=(n, 4, len(points))))


def test_points_are_kept_in_float64_and_float32_collisions_are_refused(tmp_path):
    far = 1e7 + 0.1 * np.arange(50)  # distinct in float64, 6 distinct values in float32 (the model's precision)
    with pytest.raises(DatasetError, match=r"far\.h5: points: 44 pair\(s\) of distinct points become one point in "
                                           r"float32.*points 0 and 1.*Shift and/or scale the coordinates"):
        write_dataset(tmp_path / "far.h5", _on(far, 2, 0), _on(far, 1, 1), _on(far, 1, 2))
    assert not (tmp_path / "far.h5").exists()
    shifted = far - 1e7  # what the message suggests: the same 50 points, distinct in float32 too
    path = write_dataset(tmp_path / "near.h5", _on(shifted, 2, 0), _on(shifted, 1, 1), _on(shifted, 1, 2))
    with h5py.File(path) as f:
        assert f["grids/fine"].dtype == np.float64
        np.testing.assert_array_equal(f["grids/fine"][:, 0], shifted)  # stored exactly, not rounded
    assert len(np.unique(load_split(path, "train").fine_points)) == 50

    with h5py.File(path, "r+") as f:  # a file of an older lnf, which stored the points as float32: merged
        del f["grids/coarse"], f["grids/fine"]
        _write_array(f, "grids/fine", far.astype(np.float32)[:, None])
        f["grids/coarse"] = f["grids/fine"]
        _as_before_manifests(f)
    for read in (lambda: verify_dataset(path), lambda: load_split(path, "train")):
        with pytest.raises(DatasetError, match=r"near\.h5: /grids/fine: points 0 and 1 are the same point "
                                               r"\[10000000.0\], given twice with different /train/fields.*stores "
                                               r"its points in float32"):
            read()


def test_a_point_given_twice_needs_the_same_values(tmp_path):
    points = np.r_[np.linspace(0, 1, 5), 0.5]  # point 5 repeats point 2 (a mesh node duplicated at a seam)
    with pytest.raises(DatasetError, match=r"a\.h5: points: points 2 and 5 are the same point \[0.5\], given twice "
                                           r"with different train fields \(trajectory 0, sample 0"):
        write_dataset(tmp_path / "a.h5", _on(points, 2, 0), _on(points, 1, 1), _on(points, 1, 2))
    assert not (tmp_path / "a.h5").exists()

    def seam(n: int, seed: int) -> Trajectories:  # the same values at both copies: one point, given twice
        part = _on(points, n, seed)
        part.fields[:, :, 5] = part.fields[:, :, 2]
        return Trajectories(points=points, times=part.times, fields=part.fields)

    path = write_dataset(tmp_path / "b.h5", seam(2, 0), seam(1, 1), seam(1, 2))
    assert verify_dataset(path) == path and load_split(path, "val").fine_points.shape == (6, 1)


def test_splits_sharing_a_trajectory_are_refused(tmp_path, caplog):
    points = np.linspace(0, 1, 5)
    train, val, test = _on(points, 3, 0), _on(points, 1, 1), _on(points, 2, 2)
    with pytest.raises(DatasetError, match=r"a\.h5: the test split is identical to the train split \(e\.g\. test "
                                           r"trajectory 0 is train trajectory 0.*leaks the training data"):
        write_dataset(tmp_path / "a.h5", train, val, train)
    with pytest.raises(DatasetError, match=r"1 of the 2 test trajectories is also in the train split \(e\.g\. "
                                           r"test trajectory 1 is train trajectory 2"):
        write_dataset(tmp_path / "a.h5", train, val, Trajectories.stack([test.select(0), train.select(2)]))
    with pytest.raises(DatasetError, match=r"1 of the 1 val trajectories is also in the train split"):
        write_dataset(tmp_path / "a.h5", train, train.select(1), test)
    assert not (tmp_path / "a.h5").exists()
    with caplog.at_level("WARNING", logger="lnf.trajectories"):  # val = test: written, with a warning
        path = write_dataset(tmp_path / "b.h5", train, test, test)
    assert "the test split is identical to the val split" in caplog.text and verify_dataset(path) == path


def test_edited_generation_attributes_are_found(tmp_path):
    path = write_dataset(tmp_path / "mine.h5", *_splits(), train_times=6)
    with h5py.File(path, "r+") as f:  # the training horizon edited by hand: the arrays' checksums still hold
        generation = json.loads(f.attrs["lnf_generation"])
        f.attrs["lnf_generation"] = json.dumps({**generation, "train_times": 10})
    before = _digest(path)
    message = r"mine\.h5: root attribute lnf_generation does not match its checksum in lnf_attributes_checksum"
    for read in (lambda: verify_dataset(path), lambda: load_split(path, "train"), lambda: stored_generation(path),
                 lambda: ensure_dataset(LiftedPendulum(), DatasetConfig(), path)):
        with pytest.raises(DatasetError, match=message + ".*cannot be regenerated"):
            read()
    assert _digest(path) == before  # refused, never regenerated

    with h5py.File(path, "r+") as f:  # a file of an older lnf has no attribute checksums: verified as before ...
        del f.attrs["lnf_attributes_checksum"]
    assert verify_dataset(path) == path and load_split(path, "train").train_times == 10
    with h5py.File(path, "r+") as f:  # ... and what its datasets tell is still compared
        f.attrs["lnf_generation"] = json.dumps({**generation, "n_times": 20, "observed_fraction": 0.5})
    with pytest.raises(DatasetError, match=r"mine\.h5: root attribute lnf_generation disagrees with the data: "
                                           r"n_times = 20, but the file holds 12.*observed_fraction = 0.5"):
        verify_dataset(path)


def _pendulum_arrays(scene: LiftedPendulum, n: int, T: int, points: np.ndarray, rng) -> Trajectories:
    """The pendulum's own trajectories on scattered points: what another simulator could have written."""
    states = scene.simulate(scene.sample_initial_states(n, rng), 0.05 * np.arange(T))
    q, v = scene.fields(states, points)
    kinetic, potential = scene.true_energy_parts(states)
    return Trajectories(points=points, times=0.05 * np.arange(T), fields=q, velocities=v,
                        kinetic=kinetic, potential=potential)


@pytest.mark.slow
def test_scattered_points_from_arrays_train_evaluate_and_draw(tmp_path):
    """Trajectories on 150 random points of the pendulum's square, written without a scene: training takes the
    file's settings (not data.*), the test phase evaluates on the stored points and draws them scattered, and
    lnf.evaluate refuses other times for a file without states, naming why."""
    from lnf.evaluate import evaluate
    from lnf.train import train

    scene, rng = LiftedPendulum(), np.random.default_rng(0)
    points = rng.uniform(-1, 1, (150, 2))
    parts = [_pendulum_arrays(scene, n, 16, points, rng) for n in (3, 1, 2)]
    path = write_dataset(tmp_path / "scattered.h5", *parts, train_times=8, observed_fraction=0.5)
    cfg = compose_config("train", [*TINY, "trainer=smoke", "trainer.max_epochs=1", "logger=csv", "threads=1",
                                   f"data.path={path}", "data.n_train=99", "data.n_times=50"], tmp_path)
    metrics = train(cfg)
    assert np.isfinite(metrics["field_rel_l2/all/median"]) and "energy_rel_err/max" in metrics
    assert metrics["evaluation_points"] == 150 and metrics["frames"] == 16  # the file's, not data.n_times=50
    assert (tmp_path / "out" / "figures" / "test_trajectory0.png").stat().st_size > 0

    ckpt = tmp_path / "out" / "checkpoints" / "last.ckpt"
    saved = torch.load(ckpt, map_location="cpu", weights_only=False)
    held = saved["hyper_parameters"]["data"]
    assert held["source"] == "arrays" and held["generation"]["n_train"] == 3
    from lnf.dataset import content_checksum
    from lnf.model import load

    # the checkpoint records the content checksum of the file it was trained on, which lnf.evaluate compares
    assert saved["SnapshotDataModule"]["checksum"] == content_checksum(path) == load(ckpt).checkpoint["data_checksum"]
    again = evaluate(compose_config("evaluate", [f"ckpt_path={ckpt}", "figures=0", "long_steps=0",
                                            "max_reduction_points=64"], tmp_path / "e"))
    assert again["field_rel_l2/all/median"] == pytest.approx(metrics["field_rel_l2/all/median"], rel=1e-5)
    with pytest.raises(ValueError, match="holds no full-order states; evaluation is limited to the stored times"):
        evaluate(compose_config("evaluate", [f"ckpt_path={ckpt}", "dt=0.01", "figures=0"], tmp_path / "e2"))
    with pytest.raises(ValueError, match="grid.kind=uniform: fields on other points need"):
        evaluate(compose_config("evaluate", [f"ckpt_path={ckpt}", "grid.kind=uniform", "grid.resolution=4",
                                             "figures=0"], tmp_path / "e3"))


def test_mesh_series_from_vtu_files_and_an_xdmf_time_series(tmp_path, monkeypatch):
    meshio = pytest.importorskip("meshio")
    from lnf.mesh_io import nodal_volumes, read_mesh_series

    x, y = np.meshgrid(np.linspace(0, 1, 5), np.linspace(0, 2, 4), indexing="ij")
    nodes = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]  # a 2-D mesh written with z = 0
    quads = [[i * 4 + j, (i + 1) * 4 + j, (i + 1) * 4 + j + 1, i * 4 + j + 1] for i in range(4) for j in range(3)]
    tris = [[a, b, c] for a, b, c, d in quads] + [[a, c, d] for a, b, c, d in quads]
    files = []
    for k in range(4):
        u = np.c_[np.sin(nodes[:, 0] + 0.1 * k), nodes[:, 1] * k, np.zeros(len(nodes))]
        files.append(tmp_path / f"step{k}.vtu")
        meshio.write(files[-1], meshio.Mesh(nodes, [("triangle", tris)], point_data={"u": u}))
    run = read_mesh_series(files, "u", times=0.1 * np.arange(4), components=2)
    assert run.points.shape == (20, 2) and run.fields.shape == (1, 4, 20, 2)
    assert run.weights.sum() == pytest.approx(2.0) and not run.velocities_given
    np.testing.assert_allclose(run.fields[0, 3, :, 1], nodes[:, 1] * 3, rtol=1e-6)
    quad_weights = nodal_volumes(nodes[:, :2], meshio.Mesh(nodes, [("quad", quads)]).cells, 2)
    cell = 0.25 * 2 / 3  # a quad's area: an interior node gets 4 quarters of it, a corner one quarter
    assert quad_weights.sum() == pytest.approx(2.0)
    assert quad_weights[5] == pytest.approx(cell) and quad_weights[0] == pytest.approx(cell / 4)

    monkeypatch.chdir(tmp_path)  # meshio writes the XDMF's HDF5 beside the working directory
    with meshio.xdmf.TimeSeriesWriter("run.xdmf") as writer:
        writer.write_points_cells(nodes, [("quad", quads)])
        for k in range(3):
            writer.write_data(0.5 * k, point_data={"u": np.sin(nodes[:, 0] + k), "v": np.cos(nodes[:, 0] + k)})
    series = read_mesh_series(tmp_path / "run.xdmf", "u", velocity="v")
    np.testing.assert_allclose(series.times, [0.0, 0.5, 1.0])
    assert series.velocities_given and series.fields.shape == (1, 3, 20, 1)
    with pytest.raises(DatasetError, match="no point data 'w'; it has"):
        read_mesh_series(tmp_path / "run.xdmf", "w")
    cube = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    assert nodal_volumes(cube, meshio.Mesh(cube, [("hexahedron", [list(range(8))])]).cells, 3).sum() == \
        pytest.approx(1.0)


def test_a_missing_file_for_a_scene_without_simulator_says_to_write_it(tmp_path):
    from lnf.scenes import Scene
    from lnf.training.datamodule import SnapshotDataModule

    class OnlyLagrangian(Scene):
        field_dim, bounds, energy_scale = 1, [[0.0, 1.0]], 1.0

        def params(self):
            return {}

    with pytest.raises(DatasetError, match=r"no file there, and scene 'onlylagrangian' has no simulator .*"
                                           r"lnf.trajectories.write_dataset"):
        SnapshotDataModule(OnlyLagrangian(), path=str(tmp_path / "absent.h5"))


def test_masked_arrays_are_refused_not_stored_with_their_fill_values():
    """netCDF readers return masked arrays; np.asarray drops the mask and keeps the fill values (1e20) as data."""
    good = _string(2)
    fields = np.ma.masked_array(good.fields, mask=np.zeros(good.fields.shape, bool))
    fields.mask[1, 3, 4, 0] = True
    with pytest.raises(DatasetError, match=r"fields: got a masked array with 1 masked \(missing\) values of 216 \(the "
                                           r"first at index \[1, 3, 4, 0\]\).*fill values"):
        Trajectories(points=good.points, times=good.times, fields=fields, velocities=good.velocities)
    weights = np.ma.masked_invalid([1.0, np.nan] + [1.0] * 7)
    with pytest.raises(DatasetError, match=r"weights: got a masked array with 1 masked"):
        Trajectories(points=good.points, times=good.times, fields=good.fields, weights=weights)
    unmasked = np.ma.masked_array(good.fields, mask=False)  # nothing masked: its values, as a plain array
    np.testing.assert_array_equal(Trajectories(points=good.points, times=good.times, fields=unmasked).fields,
                                  good.fields)


def test_values_that_float32_cannot_resolve_are_refused_naming_the_loss():
    """Fields of 1e4 + 1e-3·noise lost 30 % of their signal in float32; at an offset of 1e6 distinct splits even
    collapsed into one and were reported as a train/test leak."""
    base = _string(3)
    base.fields, base.velocities = base.fields.astype(np.float64), base.velocities.astype(np.float64)
    noise = 1e-3 * np.random.default_rng(1).standard_normal(base.fields.shape)
    with pytest.raises(DatasetError, match=r"^fields: lnf stores fields and velocities in float32.*changes them by up "
                                           r"to .*of their own spread.*mean of 10000.*Subtract an offset"):
        Trajectories(points=base.points, times=base.times, fields=1e4 + noise, velocities=base.velocities)
    with pytest.raises(DatasetError, match=r"^velocities: lnf stores"):
        Trajectories(points=base.points, times=base.times, fields=base.fields, velocities=1e6 + base.velocities)
    two = np.concatenate([base.fields, 1e6 + 1e-3 * base.fields], axis=-1)  # each component on its own spread
    with pytest.raises(DatasetError, match=r"component 1 of fields"):
        Trajectories(points=base.points, times=base.times, fields=two, velocities=np.zeros_like(two))
    # what the message suggests passes, and so do a constant component and values already in float32
    kept = Trajectories(points=base.points, times=base.times, fields=noise, velocities=base.velocities)
    np.testing.assert_allclose(kept.fields, noise, rtol=1e-6)
    for fields in (np.full(base.fields.shape, 0.1), (1e4 + noise).astype(np.float32)):
        Trajectories(points=base.points, times=base.times, fields=fields, velocities=base.velocities)


def _with_everything(**kw) -> tuple:
    """Three splits with weights, energies and controls: every optional dataset of a file written from arrays."""
    out = []
    for n, seed in ((3, 0), (1, 1), (2, 2)):
        part = _string(n, seed=seed, **kw)
        rng = np.random.default_rng(10 + seed)
        part.kinetic, part.potential = rng.uniform(1, 2, (2, n, 12))
        part.controls = rng.uniform(0, 1, (n, 2))
        out.append(part)
    return tuple(out)


@pytest.mark.parametrize("damage, key", [
    (lambda f: f.__delitem__("grids/weights"), "/grids/weights"),
    (lambda f: [f.__delitem__(f"{s}/controls") for s in ("train", "val", "test")], "/(train|val|test)/controls"),
    (lambda f: [f.__delitem__(f"{s}/{k}") for s in ("train", "val", "test")
                for k in ("kinetic", "potential", "energy")], "/(train|val|test)/(kinetic|potential|energy)"),
    (lambda f: f.move("val", "x") or f.move("test", "val") or f.move("x", "test"), "/test/"),
])
def test_optional_datasets_deleted_or_splits_swapped_are_found(tmp_path, damage, key):
    """Deleting /grids/weights (the data then loaded with weights=None although lnf_generation says "weights": true),
    all controls or all energies, or swapping the val and test groups (the same counts here) passed verification."""
    train, val, test = _with_everything()
    val, test = val.select([0]), test.select([0])
    path = write_dataset(tmp_path / "mine.h5", train, val, test)
    assert load_split(path, "train").weights is not None and verify_dataset(path) == path
    with h5py.File(path, "r+") as f:
        damage(f)
    with pytest.raises(DatasetError, match=rf"mine\.h5: .*{key}.*cannot be regenerated"):
        verify_dataset(path)
    with pytest.raises(DatasetError, match=r"mine\.h5: "):  # the test split is the one each of them touches
        load_split(path, "test")


def test_a_file_replaced_while_in_use_is_refused_and_named_by_evaluate(tmp_path, caplog):
    """A same-settings file with other test fields swapped in 9 s into training made the test stage report metrics on
    the new file; lnf.evaluate of a checkpoint trained on the old one said nothing."""
    import logging
    import os

    from lnf.dataset import warn_if_changed
    from lnf.training.datamodule import SnapshotDataModule

    scene, rng = LiftedPendulum(), np.random.default_rng(0)
    points = rng.uniform(-1, 1, (20, 2))
    train, val = _pendulum_arrays(scene, 3, 8, points, rng), _pendulum_arrays(scene, 1, 8, points, rng)
    path = write_dataset(tmp_path / "mine.h5", train, val, _pendulum_arrays(scene, 2, 8, points, rng))
    other = write_dataset(tmp_path / "other.h5", train, val, _pendulum_arrays(scene, 2, 8, points, rng))
    dm = SnapshotDataModule({"_target_": "lnf.scenes.LiftedPendulum"}, path=str(path), batch_size=4)
    dm.prepare_data()
    dm.setup("fit")
    first = dm.checksum
    assert first and dm.describe()["checksum"] == first and dm.state_dict() == {"path": str(path), "checksum": first}
    os.replace(other, path)
    with pytest.raises(DatasetError, match=rf"mine\.h5: the file changed while this run was using it: its content "
                                           rf"checksum was {first} when the run first verified it, it is blake2b:"):
        dm.setup("test")
    with caplog.at_level(logging.WARNING):
        warn_if_changed(path, first)
    assert f"{path} changed since the checkpoint was trained on it" in caplog.text and first in caplog.text
    assert "the metrics are those of the file as it is now" in caplog.text
    caplog.clear()
    fresh = SnapshotDataModule({"_target_": "lnf.scenes.LiftedPendulum"}, path=str(path), batch_size=4)
    fresh.prepare_data()
    with caplog.at_level(logging.WARNING):
        warn_if_changed(path, fresh.checksum)  # unchanged: no warning
        fresh.load_state_dict({"checksum": first})  # a resumed checkpoint trained on the old file
    assert caplog.text.count("changed since") == 1 and "resumed checkpoint" in caplog.text
