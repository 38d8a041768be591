"""Reusing a dataset file: ensure_dataset keeps, regenerates or refuses what is on disk."""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import time
from pathlib import Path
from typing import Any, Iterator, Optional

import h5py

from lnf.dataset.config import DatasetConfig, _differences, _kept_message, _mismatch_message, generation_attributes
from lnf.dataset.format import DAMAGED_SUFFIX, DatasetError, ERROR_HINT, SOURCE_ARRAYS, SPLITS, _Damaged, log
from lnf.dataset.generate import generate_dataset
from lnf.dataset.load import dataset_source, verify_dataset
from lnf.dataset.verify import (
    content_checksum, _check_manifest, _check_structure, _open, _read_attributes, _verify_all, _verify_attributes)


def _file_problem(path: Path, expected: dict[str, Any]) -> Optional[tuple[str, str]]:
    """None if the file at `path` is complete, intact and matches `expected`; else (kind, detail) with kind
    "outdated" (another format_version), "mismatch" (other settings: 'key: file X, config Y'; …) or
    "corrupt" (unreadable, inconsistent, a checksum mismatch or NaN/inf: the message names file and key).
    Every dataset is read once, one trajectory at a time, to verify its checksum."""
    try:
        with _open(path) as f:
            found = _read_attributes(f, path)
            version = found.get("format_version")
            if version is not None and version != expected["format_version"]:
                return "outdated", f"format_version: file {json.dumps(version)}, config {expected['format_version']}"
            diffs = _differences({k: found.get(k) for k in expected}, expected)
            if diffs:
                return "mismatch", "; ".join(diffs)
            _verify_attributes(f, path)
            _check_structure(f, path, SPLITS)
            _verify_all(f, path, SPLITS)
            _check_manifest(f, path, SPLITS)
    except _Damaged as exc:
        return "corrupt", str(exc)
    return None


def ensure_dataset(scene: Any, cfg: DatasetConfig, path: str | os.PathLike, on_mismatch: str = "regenerate",
                   overwrite_other_settings: bool = True, writable: bool = True) -> Path:
    """Return `path`, generating it if absent, corrupt, of another format version or made with other settings.

    A file is reused only if its settings match and every dataset matches its checksum and is finite.
    on_mismatch: "regenerate" (log a warning naming the file and the problem — the differing keys, or the
    damaged dataset — and regenerate) or "error" (raise DatasetError naming them).
    overwrite_other_settings: False (an explicitly chosen path, which several runs may share) → a file made
    with other settings raises DatasetError naming the differing keys with both values, under either
    on_mismatch; corrupt and outdated files are still regenerated under "regenerate".
    A file written from arrays (:func:`lnf.trajectories.write_dataset`) is only verified (:func:`verify_dataset`),
    never regenerated: lnf has no simulator for it.
    A file that is not recognisably an lnf dataset (:func:`not_lnf_dataset`: not HDF5, truncated, or HDF5 without
    lnf's root attributes) is never overwritten or deleted: with overwrite_other_settings=False (an explicit path)
    it raises DatasetError naming the file, and nothing is changed; otherwise it is regenerated under "regenerate"
    after the file is kept as ``<name>.damaged-<time>`` beside it (a warning names both).
    writable: False → nothing is ever written at `path` (lnf.evaluate, for a checkpoint's data path outside the data
    folder): a missing or unusable file raises DatasetError naming it and the problem.
    """
    if on_mismatch not in ("regenerate", "error"):
        raise DatasetError(f"data.on_mismatch must be 'regenerate' or 'error', got {on_mismatch!r}")
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        if not writable:
            raise DatasetError(f"{path}: dataset file not found (this caller does not write there)")
        return generate_dataset(scene, cfg, path)
    if not path.is_file():
        raise DatasetError(f"{path}: not a regular file (a directory, or a link to nothing); expected an lnf dataset "
                           f"(HDF5) or no file there: point data.path at a file")
    if dataset_source(path) == SOURCE_ARRAYS:  # a user's trajectories: verified, never regenerated or overwritten
        return verify_dataset(path, scene)
    foreign = not_lnf_dataset(path)
    problem = ("foreign", foreign) if foreign else _file_problem(path, generation_attributes(scene, cfg))
    if problem is None:
        log.info("reusing dataset %s", path)
        return path
    kind, detail = problem
    if kind == "foreign" and not (overwrite_other_settings and writable):
        raise DatasetError(_foreign_message(path, detail))
    if kind == "mismatch" and not overwrite_other_settings:
        raise DatasetError(_kept_message(path, detail))
    if not writable:
        raise DatasetError(f"{detail}" if kind == "corrupt" else f"{path}: {detail}")
    if on_mismatch == "error":
        if kind == "mismatch":
            raise DatasetError(_mismatch_message(path, [detail], ERROR_HINT))
        if kind == "outdated":
            raise DatasetError(f"{path}: dataset has another file format ({detail}); {ERROR_HINT}")
        raise DatasetError(f"{detail}; {ERROR_HINT}")
    reason = {"mismatch": f"settings differ ({detail})", "outdated": f"it has another file format ({detail})",
              "corrupt": detail, "foreign": detail}[kind]
    if kind != "foreign":  # lnf's own file, which its recorded settings regenerate: replaced
        log.warning("regenerating dataset %s: %s", path, reason)
        return generate_dataset(scene, cfg, path)
    with _kept_aside(path) as aside:  # not recognisably lnf's: kept, under another name, once the new file is written
        log.warning("regenerating dataset %s: %s; the file found there is kept as %s (it is not recognisably an lnf "
                    "dataset, so it is not overwritten)", path, reason, aside)
        return generate_dataset(scene, cfg, path)


def not_lnf_dataset(path: str | os.PathLike) -> Optional[str]:
    """None when the file at `path` is recognisably an lnf dataset (an HDF5 file with lnf's root attributes
    ``lnf_generation``, a JSON object, and ``lnf_scene``), else why not (the message names the file): such a file may
    be anything of the user's, and is never overwritten or deleted by lnf."""
    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            raw = f.attrs.get("lnf_generation")
            if raw is None or "lnf_scene" not in f.attrs:
                return (f"{path}: an HDF5 file that lnf did not write (it lacks lnf's root attributes lnf_generation "
                        f"and lnf_scene)")
            try:
                generation = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
            except ValueError:
                generation = None
            if not isinstance(generation, dict):
                return f"{path}: its root attribute lnf_generation is not a JSON object, as lnf writes it"
    except OSError as exc:
        return f"{path}: file is corrupt or not an HDF5 file ({exc})"
    return None


def _foreign_message(path: Path, detail: str) -> str:
    """A file that is not recognisably an lnf dataset at a path lnf must not replace it at: nothing is changed."""
    return (f"{detail}. It is not recognisably an lnf dataset, and lnf does not overwrite, move or delete such a file "
            f"at an explicitly given path (data.path, or the data path a checkpoint records): nothing was changed. "
            f"Point data.path at another file (or set data.path=null for lnf's own file under data.data_dir); if it "
            f"is a damaged lnf dataset, move it away or delete it yourself and lnf generates it again")


@contextlib.contextmanager
def _kept_aside(path: Path) -> Iterator[Path]:
    """A second name ``<name>.damaged-<time>`` for the file at `path` (a hard link; a copy where the file system has
    none) while the block regenerates `path`: kept when the block succeeds, removed when it fails (the file then
    stays at `path` as it was). Nothing is lost either way."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    aside, k = path.with_name(f"{path.name}{DAMAGED_SUFFIX}{stamp}"), 1
    while aside.exists() or aside.is_symlink():
        aside, k = path.with_name(f"{path.name}{DAMAGED_SUFFIX}{stamp}-{k}"), k + 1
    try:
        os.link(path, aside)
    except OSError:
        shutil.copy2(path, aside)
    try:
        yield aside
    except BaseException:
        if path.exists():  # the old file is still in place: the second name is not needed
            aside.unlink(missing_ok=True)
        raise


def default_path(data_dir: str | Path, scene: Any, cfg: DatasetConfig) -> Path:
    """``{data_dir}/{scene.name}-{hash of the generation attributes}.h5``: one file per parameter set."""
    attrs = json.dumps(generation_attributes(scene, cfg), sort_keys=True, default=str)
    return Path(data_dir) / f"{scene.name}-{hashlib.sha1(attrs.encode()).hexdigest()[:10]}.h5"


def in_folder(path: Path, folder: Path) -> bool:
    """Whether `path` (links resolved) lies inside `folder`."""
    try:
        return Path(path).resolve().is_relative_to(Path(folder).resolve())
    except OSError:
        return False


def evaluation_data(scene: Any, dcfg: DatasetConfig, path: Path, data_dir: Path, on_mismatch: str,
                    explicit: bool) -> Path:
    """The generated dataset of a checkpoint's data record, ready to evaluate; returns its path.

    Inside the data folder (``paths.data_dir``: $LNF_DATA_DIR, else $LNF_ROOT/data) `path` is ensured as training
    does (generated, or regenerated, there). Outside it, nothing is written to `path` (a checkpoint, which may come
    from anywhere, names it): it is used when it holds an intact lnf dataset of the recorded settings; else (missing,
    damaged, other settings, or not an lnf dataset at all) the dataset of those settings is generated — or reused —
    at lnf's own file for them in the data folder, with a warning naming both files."""
    if in_folder(path, data_dir):
        ensure_dataset(scene, dcfg, path, on_mismatch=on_mismatch, overwrite_other_settings=not explicit)
        return path
    try:
        return ensure_dataset(scene, dcfg, path, on_mismatch="error", overwrite_other_settings=False, writable=False)
    except DatasetError as err:
        own = default_path(data_dir, scene, dcfg)
        log.warning("the checkpoint's data file is not used (%s). It lies outside the data folder %s, and "
                    "lnf.evaluate writes only inside it (paths.data_dir, $LNF_DATA_DIR): the test trajectories of the "
                    "checkpoint's data settings are taken from %s there instead (generated if not there yet)",
                    err, data_dir, own)
        ensure_dataset(scene, dcfg, own, on_mismatch=on_mismatch)
        return own


def warn_if_changed(path: Path, trained: Optional[str]) -> None:
    """A warning naming `path` when its content checksum differs from `trained`, the one recorded when the
    checkpoint was trained on it (nothing when the checkpoint records none)."""
    if not trained:
        return
    now = content_checksum(path)
    if now != trained:
        log.warning("%s changed since the checkpoint was trained on it: its content checksum was %s then, it is %s "
                    "now (the file was replaced or rewritten with other values); the metrics are those of the file as "
                    "it is now", path, trained, now)
