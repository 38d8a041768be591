"""Dataset integrity (lnf.dataset): per-dataset checksums, NaN/inf on reuse, full disks, fitting fix hints, and
explicit data.path files shared by runs with other settings (SnapshotDataModule)."""
from __future__ import annotations

import errno
import hashlib
import logging
import shutil
import subprocess
import sys
import textwrap
from collections import namedtuple
from dataclasses import asdict, replace
from pathlib import Path

import h5py
import numpy as np
import pytest

import lnf.dataset as dataset_module
from lnf.dataset import (CHECKSUM_ATTR, FORMAT_VERSION, DatasetConfig, DatasetError, dataset_keys, ensure_dataset,
                         generate_dataset, generation_attributes, load_split)
from lnf.dataset.generate import _needed_bytes
from lnf.dataset.reuse import _file_problem
from lnf.scenes import LiftedPendulum
from lnf.training.datamodule import SnapshotDataModule
from tiny_dataset import CFG, fresh_file, scene, shared_file  # noqa: F401 (fixtures)

GEN = asdict(CFG)  # the same settings as data.* keys of a SnapshotDataModule
SCENE_SPEC = {"_target_": "lnf.scenes.LiftedPendulum"}
DiskUsage = namedtuple("DiskUsage", "total used free")
# the disk tests patch shutil.disk_usage, which lnf.dataset calls as shutil.disk_usage(path.parent)


def temporaries(directory: Path) -> list[str]:
    return [p.name for p in directory.iterdir() if ".tmp-" in p.name]


def assert_same_contents(a: Path, b: Path) -> None:
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        for key in dataset_keys():
            np.testing.assert_array_equal(fa[key][...], fb[key][...], err_msg=key)
            assert fa[key].attrs[CHECKSUM_ATTR] == fb[key].attrs[CHECKSUM_ATTR]


# -- checksums -------------------------------------------------------------------------------------------
def test_every_dataset_carries_the_blake2b_of_its_values(shared_file):
    assert FORMAT_VERSION == 2
    with h5py.File(shared_file, "r") as f:
        assert f.attrs["format_version"] == 2
        found = set()
        f.visititems(lambda name, obj: found.add(name) if isinstance(obj, h5py.Dataset) else None)
        assert found == set(dataset_keys())
        for key in dataset_keys():
            data = f[key][...]
            expected = "blake2b:" + hashlib.blake2b(np.ascontiguousarray(data).tobytes()).hexdigest()
            assert f[key].attrs[CHECKSUM_ATTR] == expected, key
    assert _file_problem(shared_file, generation_attributes(LiftedPendulum(), CFG)) is None


def _zero_some_coarse_fields(path: Path) -> None:
    """Zero a slab of /train/coarse_fields in place: values stay finite, attributes intact."""
    with h5py.File(path, "r+") as f:
        ds = f["train/coarse_fields"]
        assert np.abs(ds[1, 2:4]).max() > 0
        ds[1, 2:4] = np.zeros_like(ds[1, 2:4])
        assert np.isfinite(ds[...]).all()


def test_zeroed_bytes_are_regenerated(fresh_file, shared_file, scene, caplog):
    _zero_some_coarse_fields(fresh_file)
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
        assert ensure_dataset(scene, CFG, fresh_file) == fresh_file
    warning = caplog.text
    assert "regenerating" in warning and str(fresh_file) in warning and "/train/coarse_fields" in warning
    assert "checksum" in warning
    assert_same_contents(fresh_file, shared_file)  # fixed: the deterministic generation again
    mtime = fresh_file.stat().st_mtime_ns
    assert ensure_dataset(scene, CFG, fresh_file, on_mismatch="error") == fresh_file  # its checksums hold
    assert fresh_file.stat().st_mtime_ns == mtime
    assert temporaries(fresh_file.parent) == []


def test_zeroed_bytes_error_mode_names_file_and_key(fresh_file, scene):
    _zero_some_coarse_fields(fresh_file)
    before = fresh_file.read_bytes()
    with pytest.raises(DatasetError) as err:
        ensure_dataset(scene, CFG, fresh_file, on_mismatch="error")
    msg = str(err.value)
    assert str(fresh_file) in msg and "/train/coarse_fields" in msg and "checksum" in msg
    assert "data.on_mismatch=regenerate" in msg and "delete the file" in msg
    assert fresh_file.read_bytes() == before  # refused, not touched
    # load_split verifies what it reads: the damaged split is refused, the others load
    with pytest.raises(DatasetError, match=r"pendulum\.h5: dataset /train/coarse_fields does not match"):
        load_split(fresh_file, "train")
    assert load_split(fresh_file, "test", scene=scene, cfg=CFG).coarse_fields.shape == (2, 12, 64, 1)


@pytest.mark.parametrize("key, value", [("val/velocities", np.nan), ("test/energy", np.inf), ("grids/fine", np.nan)])
def test_non_finite_values_are_regenerated(fresh_file, shared_file, scene, caplog, key, value):
    with h5py.File(fresh_file, "r+") as f:
        index = (0,) * f[key].ndim
        f[key][index] = value
    with pytest.raises(DatasetError, match=rf"pendulum\.h5: dataset /{key} contains 1 non-finite"):
        ensure_dataset(scene, CFG, fresh_file, on_mismatch="error")
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
        ensure_dataset(scene, CFG, fresh_file)
    assert f"/{key} contains 1 non-finite" in caplog.text and str(fresh_file) in caplog.text
    assert_same_contents(fresh_file, shared_file)


def test_missing_checksum_is_corrupt(fresh_file, scene):
    with h5py.File(fresh_file, "r+") as f:
        del f["test/masks"].attrs[CHECKSUM_ATTR]
    with pytest.raises(DatasetError, match=rf"/test/masks has no {CHECKSUM_ATTR} attribute"):
        ensure_dataset(scene, CFG, fresh_file, on_mismatch="error")
    with pytest.raises(DatasetError, match=rf"/test/masks has no {CHECKSUM_ATTR}"):
        load_split(fresh_file, "test")


def test_edited_root_attributes_are_corrupt(fresh_file, scene, caplog):
    """The settings edited by hand to those of another run (training horizon 5, not 6): every dataset's checksum
    still holds, the checksum of lnf_generation does not; the file is not reused with data it does not hold."""
    other = replace(CFG, train_times=5)
    with h5py.File(fresh_file, "r+") as f:
        f.attrs["lnf_generation"] = f.attrs["lnf_generation"].replace('"train_times": 6', '"train_times": 5')
    message = r"pendulum\.h5: root attribute lnf_generation does not match its checksum in lnf_attributes_checksum"
    with pytest.raises(DatasetError, match=message + r".*data\.on_mismatch=regenerate"):
        ensure_dataset(scene, other, fresh_file, on_mismatch="error")
    with pytest.raises(DatasetError, match=message):
        load_split(fresh_file, "test")
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
        assert ensure_dataset(scene, other, fresh_file, overwrite_other_settings=False) == fresh_file
    assert "regenerating" in caplog.text and "lnf_generation does not match its checksum" in caplog.text
    assert load_split(fresh_file, "test", scene=scene, cfg=other).train_times == 5
    with h5py.File(fresh_file, "r+") as f:  # a file of an older lnf has no attribute checksums: reused as before
        del f.attrs["lnf_attributes_checksum"]
    mtime = fresh_file.stat().st_mtime_ns
    assert ensure_dataset(scene, other, fresh_file, on_mismatch="error") == fresh_file
    assert fresh_file.stat().st_mtime_ns == mtime


def test_a_version_1_file_is_regenerated(fresh_file, shared_file, scene, caplog):
    with h5py.File(fresh_file, "r+") as f:
        f.attrs["format_version"] = 1
        for key in dataset_keys():
            del f[key].attrs[CHECKSUM_ATTR]
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
        ensure_dataset(scene, CFG, fresh_file, overwrite_other_settings=False)  # not "other settings"
    assert "format_version: file 1, config 2" in caplog.text
    assert_same_contents(fresh_file, shared_file)


def test_verification_reads_one_trajectory_at_a_time(shared_file, monkeypatch):
    """Bounded memory: with a block budget below one trajectory, no read covers two of them."""
    monkeypatch.setattr(dataset_module.verify, "BLOCK_BYTES", 1, raising=False)
    reads: dict[str, list[int]] = {}
    original = h5py.Dataset.read_direct

    def spy(self, dest, source_sel=None, dest_sel=None):
        reads.setdefault(self.name, []).append(np.asarray(dest[dest_sel] if dest_sel is not None else dest).shape[0])
        return original(self, dest, source_sel, dest_sel)

    monkeypatch.setattr(h5py.Dataset, "read_direct", spy)
    assert _file_problem(shared_file, generation_attributes(LiftedPendulum(), CFG)) is None
    for split, n in (("train", 3), ("val", 1), ("test", 2)):
        for key in ("fields", "velocities", "coarse_fields", "coarse_velocities", "states"):
            assert reads[f"/{split}/{key}"] == [1] * n


# -- full disks ------------------------------------------------------------------------------------------
def test_not_enough_space_fails_before_any_temporary(tmp_path, scene, monkeypatch):
    monkeypatch.setattr(shutil, "disk_usage", lambda p: DiskUsage(10 ** 9, 10 ** 9 - 300_000, 300_000))
    opened = []
    monkeypatch.setattr(dataset_module.verify.h5py, "File", lambda *a, **k: opened.append(a) or pytest.fail("opened"))
    target = tmp_path / "d.h5"
    with pytest.raises(DatasetError) as err:
        ensure_dataset(scene, CFG, target)
    msg = str(err.value)
    assert str(target) in msg and "not enough free disk space" in msg
    assert "needs about 1.2 MB" in msg and "0.3 MB free" in msg
    assert opened == [] and list(tmp_path.iterdir()) == []


def test_not_enough_space_keeps_an_older_file(fresh_file, scene, monkeypatch):
    before = fresh_file.read_bytes()
    big = replace(CFG, n_train=6000, fine_resolution=64)  # 2.4 GB: checked before anything is simulated
    needed = _needed_bytes(6003, 12, 2, 64 * 64, 64, 2, 1)
    assert 2.4e9 < needed < 2.5e9
    monkeypatch.setattr(shutil, "disk_usage", lambda p: DiskUsage(10 ** 12, 10 ** 12 - 2 * 10 ** 9, 2 * 10 ** 9))
    with pytest.raises(DatasetError, match=rf"pendulum\.h5: not enough free disk space to generate the dataset: it "
                                           rf"needs about {needed / 1e9:.2f} GB, .* has 2\.00 GB free"):
        ensure_dataset(scene, big, fresh_file)
    assert fresh_file.read_bytes() == before and temporaries(fresh_file.parent) == []


def _fail_in_second_split(monkeypatch):
    original = dataset_module.generate._write_split
    calls = []

    def write_split(group, *args, **kwargs):
        calls.append(group.name)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return original(group, *args, **kwargs)

    monkeypatch.setattr(dataset_module.generate, "_write_split", write_split)


def _fail_in_fields(monkeypatch, scene):
    original, calls = scene.fields, []

    def fields(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:  # inside the first split's trajectory loop
            raise OSError(errno.ENOSPC, "No space left on device")
        return original(*args, **kwargs)

    monkeypatch.setattr(scene, "fields", fields)


@pytest.mark.parametrize("where", ["split", "fields"])
def test_no_space_while_writing_keeps_the_older_file(fresh_file, monkeypatch, where):
    scene = LiftedPendulum()
    _fail_in_second_split(monkeypatch) if where == "split" else _fail_in_fields(monkeypatch, scene)
    before = fresh_file.read_bytes()
    with pytest.raises(DatasetError) as err:
        ensure_dataset(scene, replace(CFG, seed=5), fresh_file)
    msg = str(err.value)
    assert str(fresh_file) in msg and "No space left on device" in msg and "space" in msg and "MB" in msg
    assert isinstance(err.value.__cause__, OSError)
    assert temporaries(fresh_file.parent) == [] and fresh_file.read_bytes() == before


def test_no_space_while_writing_leaves_no_file(tmp_path, scene, monkeypatch):
    _fail_in_second_split(monkeypatch)
    target = tmp_path / "d.h5"
    with pytest.raises(DatasetError, match=r"d\.h5: writing the dataset failed \(No space left on device\); "
                                           r"it needs about 1\.2 MB of disk space"):
        ensure_dataset(scene, CFG, target)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_FSIZE/SIGXFSZ semantics of Linux")
def test_a_real_write_failure_does_not_crash(tmp_path):
    """The kernel refuses to grow the file (RLIMIT_FSIZE, as a full disk refuses blocks): HDF5 used to crash
    (SIGSEGV) on the failed writes; now the space reservation fails first, cleanly."""
    target = tmp_path / "d.h5"
    code = textwrap.dedent(f"""
        import resource, signal
        from lnf.dataset import DatasetConfig, DatasetError, generate_dataset
        from lnf.scenes import LiftedPendulum
        cfg = DatasetConfig(**{GEN!r})
        scene = LiftedPendulum()
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a too-large write fails with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (65536, resource.RLIM_INFINITY))
        try:
            generate_dataset(scene, cfg, {str(target)!r})
        except DatasetError as exc:
            print("DatasetError:", exc)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert f"DatasetError: {target}: writing the dataset failed" in proc.stdout and "disk space" in proc.stdout
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("gen", [GEN, dict(GEN, n_times=400, fine_resolution=4, coarse_resolution=2)])
def test_size_estimate_bounds_the_file_and_the_reservation_is_released(tmp_path, scene, gen):
    cfg = DatasetConfig(**gen)
    path = generate_dataset(scene, cfg, tmp_path / "d.h5")
    n = cfg.n_train + cfg.n_val + cfg.n_test
    needed = _needed_bytes(n, cfg.n_times, 2, cfg.fine_resolution ** 2, cfg.coarse_resolution ** 2, 2, 1)
    size = path.stat().st_size
    assert size < needed - (1 << 19)  # HDF5 truncated the reserved file to its contents
    with h5py.File(path, "r") as f:
        data = sum(f[key].nbytes for key in dataset_keys())
    assert data < size < needed


# -- fix hints -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("damage", ["garbage", "zeroed", "nan"])
def test_hints_fit_the_situation(fresh_file, scene, caplog, monkeypatch, damage):
    if damage == "garbage":
        fresh_file.write_bytes(b"not HDF5\n" * 20)
    elif damage == "zeroed":
        _zero_some_coarse_fields(fresh_file)
    else:
        with h5py.File(fresh_file, "r+") as f:
            f["train/fields"][0, 0, 0, 0] = np.nan
    # under "error": how to regenerate
    with pytest.raises(DatasetError) as err:
        ensure_dataset(scene, CFG, fresh_file, on_mismatch="error")
    assert "set data.on_mismatch=regenerate" in str(err.value) and "delete the file" in str(err.value)
    # load_split does not regenerate, and does not send the user to delete what is regenerated automatically
    with pytest.raises(DatasetError) as err:
        load_split(fresh_file, "train")
    assert "delete" not in str(err.value) and "ensure_dataset regenerates it" in str(err.value)
    # regeneration failing (a full disk): the error is about space, no on_mismatch advice
    monkeypatch.setattr(shutil, "disk_usage", lambda p: DiskUsage(10 ** 9, 10 ** 9, 0))
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"), pytest.raises(DatasetError) as err:
        ensure_dataset(scene, CFG, fresh_file)
    assert "not enough free disk space" in str(err.value) and "on_mismatch" not in str(err.value)
    monkeypatch.undo()
    # automatic regeneration: the warning names the problem, not a setting that is already in force
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
        ensure_dataset(scene, CFG, fresh_file)
    assert "regenerating dataset" in caplog.text and str(fresh_file) in caplog.text
    assert "on_mismatch" not in caplog.text and "delete" not in caplog.text


def test_settings_mismatch_hints(fresh_file, scene):
    with pytest.raises(DatasetError) as err:
        ensure_dataset(scene, replace(CFG, n_train=4), fresh_file, on_mismatch="error")
    assert "generation.n_train: file 3, config 4" in str(err.value) and "set data.on_mismatch=regenerate" in str(err.value)
    with pytest.raises(DatasetError) as err:
        load_split(fresh_file, "test", cfg=replace(CFG, n_train=4))
    assert "generation.n_train: file 3, config 4" in str(err.value) and "delete" not in str(err.value)


# -- explicit data.path shared by runs with other settings -----------------------------------------------
def _module(**kwargs) -> SnapshotDataModule:
    return SnapshotDataModule(SCENE_SPEC, batch_size=4, **{**GEN, **kwargs})


@pytest.mark.parametrize("on_mismatch", ["regenerate", "error"])
def test_explicit_path_is_not_overwritten_with_other_settings(tmp_path, on_mismatch):
    shared = tmp_path / "shared.h5"
    first = _module(path=str(shared))
    first.prepare_data()
    before, mtime = shared.read_bytes(), shared.stat().st_mtime_ns
    second = _module(path=str(shared), n_train=4, seed=3, on_mismatch=on_mismatch)
    with pytest.raises(DatasetError) as err:
        second.prepare_data()
    msg = str(err.value)
    assert str(shared) in msg and "generated with other settings" in msg
    assert "generation.n_train: file 3, config 4" in msg and "generation.seed: file 0, config 3" in msg
    assert "another data.path" in msg and "path: null" in msg and "delete the file" in msg
    assert "on_mismatch" not in msg  # regenerating would only start the back and forth
    assert shared.read_bytes() == before and shared.stat().st_mtime_ns == mtime
    first.prepare_data()  # the first run keeps reusing its file
    assert shared.stat().st_mtime_ns == mtime and first.split("train").states.shape[0] == 3


def test_explicit_path_damaged_file_is_still_regenerated(tmp_path, caplog):
    shared = tmp_path / "shared.h5"
    dm = _module(path=str(shared))
    dm.prepare_data()
    _zero_some_coarse_fields(shared)
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
        _module(path=str(shared)).prepare_data()
    assert "/train/coarse_fields" in caplog.text
    assert _file_problem(shared, generation_attributes(dm.scene, dm.config)) is None


def test_default_paths_keep_one_file_per_setting_set(tmp_path):
    a, b = _module(data_dir=str(tmp_path)), _module(data_dir=str(tmp_path), n_train=4)
    a.prepare_data()
    b.prepare_data()
    assert a.path != b.path and a.path.parent == b.path.parent == tmp_path
    assert not a.explicit_path and _module(path=str(tmp_path / "x.h5")).explicit_path
    # ensure_dataset's default still regenerates another setting set's file
    ensure_dataset(b.scene, b.config, a.path)
    assert load_split(a.path, "train").states.shape[0] == 4


def test_datamodule_verifies_once_until_the_file_changes(tmp_path, monkeypatch, caplog):
    """prepare_data and setup both ensure the dataset: the second verification is skipped while the file
    is unchanged, and redone (here: regenerating it) once it was written."""
    import lnf.dataset.snapshots as datamodule_module  # where SnapshotDataModule.prepare_data calls it

    calls = []
    original = datamodule_module.ensure_dataset
    monkeypatch.setattr(datamodule_module, "ensure_dataset", lambda *a, **k: calls.append(1) or original(*a, **k))
    dm = _module(path=str(tmp_path / "d.h5"))
    dm.prepare_data()
    dm.setup("fit")
    assert len(calls) == 1
    _zero_some_coarse_fields(dm.path)
    with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
        dm.setup("fit")
    assert len(calls) == 2 and "/train/coarse_fields" in caplog.text
    dm.prepare_data()
    assert len(calls) == 2


# -- files that are not lnf's: never overwritten or deleted ----------------------------------------------
def _users_files(tmp_path: Path) -> list[Path]:
    """A text file, and a foreign HDF5 file that happens to carry format_version = 1 (lnf regenerated both)."""
    text = tmp_path / "victim.txt"
    text.write_text("the user's notes\n")
    foreign = tmp_path / "results.h5"
    with h5py.File(foreign, "w") as f:
        f.attrs["format_version"] = 1
        f["x"] = np.arange(5.0)
    return [text, foreign]


@pytest.mark.parametrize("on_mismatch", ["regenerate", "error"])
def test_an_explicit_path_holding_a_file_lnf_did_not_write_is_refused_unchanged(tmp_path, on_mismatch):
    for victim in _users_files(tmp_path):
        before = victim.read_bytes()
        with pytest.raises(DatasetError) as err:
            _module(path=str(victim), on_mismatch=on_mismatch).prepare_data()
        msg = str(err.value)
        assert str(victim) in msg and "not recognisably an lnf dataset" in msg and "nothing was changed" in msg
        assert "another file" in msg and "data.path=null" in msg
        assert victim.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [
            "results.h5", "victim.txt"]


def test_a_file_lnf_did_not_write_is_kept_aside_before_regeneration(tmp_path, scene, caplog, monkeypatch):
    """At lnf's own default path (overwrite_other_settings=True), the file found there is kept under another name."""
    for victim in _users_files(tmp_path):
        before = victim.read_bytes()
        monkeypatch.setattr(shutil, "disk_usage", lambda p: DiskUsage(10 ** 9, 10 ** 9, 0))
        with pytest.raises(DatasetError, match="not enough free disk space"):  # a failed regeneration keeps it in place
            ensure_dataset(scene, CFG, victim)
        monkeypatch.undo()
        assert victim.read_bytes() == before and not list(tmp_path.glob(f"{victim.name}.damaged-*"))
        with caplog.at_level(logging.WARNING, logger="lnf.dataset"):
            ensure_dataset(scene, CFG, victim)
        (aside,) = tmp_path.glob(f"{victim.name}.damaged-*")
        assert aside.read_bytes() == before and f"is kept as {aside}" in caplog.text
        assert _file_problem(victim, generation_attributes(scene, CFG)) is None


def test_a_checkpoint_data_path_outside_the_data_folder_is_never_written(tmp_path, scene, shared_file, caplog):
    """A crafted checkpoint's data.path = /tmp/x/victim.txt made lnf.evaluate replace victim.txt with an HDF5 file."""
    from lnf.dataset import default_path, evaluation_data

    data_dir = tmp_path / "data"
    elsewhere = tmp_path / "x"
    elsewhere.mkdir()
    victims = _users_files(elsewhere)
    for victim in victims:
        before = victim.read_bytes()
        for explicit in (False, True):
            with caplog.at_level(logging.WARNING):
                got = evaluation_data(scene, CFG, victim, data_dir, "regenerate", explicit)
            assert got == default_path(data_dir, scene, CFG) and victim.read_bytes() == before
            assert str(victim) in caplog.text and "lies outside the data folder" in caplog.text
    assert sorted(p.name for p in elsewhere.iterdir()) == ["results.h5", "victim.txt"]
    assert _file_problem(got, generation_attributes(scene, CFG)) is None
    # an intact file of the recorded settings outside the folder is used as it is, read-only
    copy = elsewhere / "pendulum.h5"
    copy.write_bytes(shared_file.read_bytes())
    mtime = copy.stat().st_mtime_ns
    assert evaluation_data(scene, CFG, copy, data_dir, "regenerate", True) == copy
    _zero_some_coarse_fields(copy)  # damaged outside: not regenerated there
    mtime = copy.stat().st_mtime_ns
    assert evaluation_data(scene, CFG, copy, data_dir, "regenerate", False) == got
    assert copy.stat().st_mtime_ns == mtime
    # inside the data folder: as training does (a damaged lnf file regenerated; a foreign one refused when explicit)
    inside = data_dir / "victim.txt"
    inside.write_text("notes")
    with pytest.raises(DatasetError, match="not recognisably an lnf dataset"):
        evaluation_data(scene, CFG, inside, data_dir, "regenerate", True)
    assert inside.read_text() == "notes"


def test_swapped_or_deleted_datasets_of_a_generated_file_are_found(fresh_file, scene):
    with h5py.File(fresh_file, "r+") as f:  # the val and test groups swapped
        f.move("val", "x"), f.move("test", "val"), f.move("x", "test")
    kind, detail = _file_problem(fresh_file, generation_attributes(scene, CFG))
    assert kind == "corrupt" and "holds other values than were written there" in detail
    with pytest.raises(DatasetError, match=r"pendulum\.h5: dataset /val/\w+ holds other values"):
        load_split(fresh_file, "val")
    with h5py.File(fresh_file, "r+") as f:
        f.move("val", "x"), f.move("test", "val"), f.move("x", "test")
        f.attrs["lnf_manifest"] = "{}"  # the manifest edited: its attribute checksum no longer holds
    with pytest.raises(DatasetError, match="root attribute lnf_manifest does not match its checksum"):
        load_split(fresh_file, "val")
