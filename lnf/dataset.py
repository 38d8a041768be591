"""Ground-truth trajectory datasets in HDF5 (docs/method.md §7.1): generation, reuse checks, loading.

A dataset file holds, for the splits ``train``/``val``/``test`` (disjoint trajectories), the full-order
states, their energies, and the configuration and velocity fields sampled on a fine evaluation grid and
on a coarse observation grid, plus each trajectory's fixed random mask of observed coarse points.

Layout (``FORMAT_VERSION`` 2)::

    attrs: format_version (int), lnf_scene (json of scene.spec()), lnf_generation (json of the
           DatasetConfig), scene_name (str)
    /times                       (T,)            float64  [s], t_k = dt·k
    /grids/fine                  (Nf, dim_B)     float64  midpoint grid, fine_resolution per axis
    /grids/coarse                (Nc, dim_B)     float64  midpoint (or vertex) grid, coarse_resolution per axis
    /{split}/states              (n, T, S)       float64
    /{split}/energy              (n, T)          float64  scene.true_energy
    /{split}/fields              (n, T, Nf, A)   float32  q on the fine grid
    /{split}/velocities          (n, T, Nf, A)   float32  q̇ on the fine grid
    /{split}/coarse_fields       (n, T, Nc, A)   float32
    /{split}/coarse_velocities   (n, T, Nc, A)   float32
    /{split}/masks               (n, Nc)         bool     exactly round(observed_fraction·Nc) True per row

A file written from a user's arrays (:func:`lnf.trajectories.write_dataset`) has ``lnf_generation["source"] =
"arrays"`` and its own settings (counts, dt, train_times, observed_fraction, seed), points in any order as
``/grids/fine`` (``/grids/coarse`` and the coarse fields are links to them), states of width S = 0 when none
were given, and optionally ``/grids/weights`` (Nf,), ``/{split}/kinetic`` and ``/{split}/potential`` (n, T)
(then ``energy`` is their sum; without them it is absent) and ``/{split}/controls`` (n, c). Such a file is
verified before use but never regenerated.

Every dataset carries the attribute ``lnf_checksum = "blake2b:<hex>"``: BLAKE2b (64-byte digest) of its
values as little-endian bytes in C order (version 2 adds it; version 1 files are regenerated). The root attribute
``lnf_attributes_checksum`` holds the checksum of each root attribute (``ROOT_ATTRIBUTES``): one edited after writing
makes the file damaged (files without it, written by older lnf, are verified as before).

Files are written atomically (temporary file, then ``os.replace``), so a file at the target path is
always complete; a temporary left by a killed writer is removed by the next generation of that file.
Before writing, the free space is checked and the file's size is reserved (``posix_fallocate``), so a full
disk fails cleanly before HDF5 writes (HDF5 can crash on a failed write). A reused file is verified:
every checksum, and every float value finite (read one trajectory at a time); a damaged file is
regenerated (``on_mismatch="regenerate"``) or refused (``"error"``). A file at an explicitly chosen path
is never overwritten with other settings when ``overwrite_other_settings=False`` (the DataModule's
choice for an explicit ``data.path``). A file that is not recognisably an lnf dataset (:func:`not_lnf_dataset`) is
never overwritten or deleted: refused at an explicit path, else kept as ``<name>.damaged-<time>`` before
regeneration. The root attribute ``lnf_manifest`` (``{dataset path: its lnf_checksum}``, covered by
``lnf_attributes_checksum``) lists every dataset written: one deleted, added, moved or swapped (the val and test
groups) makes the file damaged. :func:`content_checksum` identifies what a file holds (a run refuses a file replaced
while in use). Every user-facing failure raises :class:`DatasetError` naming the file and the key.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import errno
import hashlib
import io
import json
import logging
import math
import multiprocessing
import os
import shutil
import socket
import time
from dataclasses import asdict, dataclass, fields as dataclass_fields
from glob import escape as glob_escape
from pathlib import Path
from typing import Any, Iterator, Mapping, Optional

import h5py
import numpy as np

from lnf.progress import progress_bar
from lnf.quadrature import midpoint_grid, vertex_grid
from lnf.tempfiles import write_bytes_atomic, writer_is_gone

FORMAT_VERSION = 2
SPLITS = ("train", "val", "test")
COARSE_GRIDS = ("centres", "vertices")
CHECKSUM_ATTR = "lnf_checksum"
CHECKSUM_ALGORITHM = "blake2b"
ATTRIBUTES_CHECKSUM_ATTR = "lnf_attributes_checksum"  # root attribute: json {attribute: checksum} of ROOT_ATTRIBUTES
ROOT_ATTRIBUTES = ("format_version", "lnf_scene", "lnf_generation", "scene_name")
# root attribute: json {dataset key: its lnf_checksum} of every dataset written, so a dataset deleted, moved or
# swapped with another (the val and test groups) after writing is found; covered by lnf_attributes_checksum
MANIFEST_ATTR = "lnf_manifest"
DAMAGED_SUFFIX = ".damaged-"  # a file not recognisably lnf's, kept aside before regeneration: <name>.damaged-<time>
FIELD_KEYS = ("fields", "velocities", "coarse_fields", "coarse_velocities")
SPLIT_KEYS = ("states", "energy", "masks") + FIELD_KEYS
OPTIONAL_SPLIT_KEYS = ("kinetic", "potential", "controls")  # only in files written from arrays
SOURCE_ARRAYS = "arrays"  # lnf_generation["source"] of a file written by lnf.trajectories.write_dataset
# fix hints, by situation: ensure_dataset under on_mismatch="error" (regeneration is not automatic) ...
ERROR_HINT = "set data.on_mismatch=regenerate to regenerate it, or delete the file"
FIX_HINT = ERROR_HINT  # the name of earlier versions
# ... and load_split, which does not regenerate, but ensure_dataset (run first by lnf.train/lnf.evaluate) does
LOAD_HINT = ("lnf.dataset.ensure_dataset regenerates it (lnf.train and lnf.evaluate run it first, with the "
             "default data.on_mismatch=regenerate)")
# ... and a file written from a user's arrays, which lnf cannot regenerate
ARRAYS_HINT = ("it was written from arrays (lnf.trajectories.write_dataset) and cannot be regenerated by lnf: "
               "write it again from your simulator's output")
BLOCK_BYTES = 4 << 20  # verification reads blocks of whole rows (trajectories) of at most this size (≥ 1 row)

log = logging.getLogger("lnf.dataset")


class DatasetError(ValueError):
    """A dataset file or dataset setting is unusable; the message names the file/key and the fix."""


class _Damaged(DatasetError):
    """A damaged file (unreadable, missing or inconsistent dataset, bad checksum, NaN/inf): the message names
    the file and the key but no fix, which depends on the caller (regenerated, refused, or only loaded)."""


# ---------------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------------
def _as_int(key: str, value: Any, minimum: int) -> int:
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if isinstance(value, float) and value.is_integer():
        ok, value = True, int(value)
    if not ok or int(value) < minimum:
        raise DatasetError(f"data.{key} must be an integer ≥ {minimum}, got {value!r}")
    return int(value)


def _as_float(key: str, value: Any) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise DatasetError(f"data.{key} must be a number, got {value!r}")
    if not math.isfinite(float(value)):
        raise DatasetError(f"data.{key} must be finite, got {value!r}")
    return float(value)


@dataclass
class DatasetConfig:
    """How a dataset is generated (stored in the file; any change regenerates it).

    Attributes:
        n_train, n_val, n_test: trajectories per split (disjoint).
        n_times: samples per trajectory; dt: sample spacing [s], t_k = dt·k, k = 0..n_times−1.
        train_times: the first samples used for training (time split; docs/method.md §7.1).
        fine_resolution: evaluation grid, fine_resolution^dim_B cell centres.
        coarse_resolution: observation grid, coarse_resolution^dim_B points.
        coarse_grid: ``"centres"``: the cell centres of that many cells per axis (the paper's); ``"vertices"``:
            that many equally spaced points per axis from one face of the box to the other, so the observations
            reach the boundary, where a field such as the pendulum's Legendre mode is largest.
        observed_fraction: fraction of the coarse grid each trajectory observes (fixed random subset).
        seed: seed of initial states and masks.
    """

    n_train: int = 32
    n_val: int = 8
    n_test: int = 16
    n_times: int = 100
    dt: float = 0.05
    train_times: int = 50
    fine_resolution: int = 64
    coarse_resolution: int = 32
    observed_fraction: float = 0.25
    seed: int = 0
    coarse_grid: str = "centres"

    def __post_init__(self) -> None:
        for key in ("n_train", "n_val", "n_test", "n_times", "train_times", "fine_resolution",
                    "coarse_resolution"):
            setattr(self, key, _as_int(key, getattr(self, key), 1))
        self.seed = _as_int("seed", self.seed, 0)
        self.dt = _as_float("dt", self.dt)
        self.observed_fraction = _as_float("observed_fraction", self.observed_fraction)
        if self.dt <= 0:
            raise DatasetError(f"data.dt must be > 0 [s], got {self.dt!r}")
        if self.train_times > self.n_times:
            raise DatasetError(f"data.train_times must be ≤ data.n_times = {self.n_times}, got {self.train_times}")
        if not 0 < self.observed_fraction <= 1:
            raise DatasetError(f"data.observed_fraction must be in (0, 1], got {self.observed_fraction!r}")
        if self.coarse_grid not in COARSE_GRIDS:
            raise DatasetError(f"data.coarse_grid must be one of {', '.join(COARSE_GRIDS)}, got {self.coarse_grid!r}")
        if self.coarse_grid == "vertices" and self.coarse_resolution < 2:
            raise DatasetError("data.coarse_grid=vertices needs data.coarse_resolution ≥ 2 (a point on each face), "
                               f"got {self.coarse_resolution}")

    def record(self) -> dict[str, Any]:
        """The settings a file records (json-able). ``coarse_grid`` appears only when it is not the default
        "centres", so files written before the setting existed keep matching their configuration."""
        values = asdict(self)
        if values["coarse_grid"] == "centres":
            del values["coarse_grid"]
        return values

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], ignore: tuple[str, ...] = ()) -> "DatasetConfig":
        """Build from a mapping (e.g. a Hydra ``data`` node); unknown keys not in `ignore` are an error."""
        known = {f.name for f in dataclass_fields(cls)}
        unknown = sorted(set(values) - known - set(ignore))
        if unknown:
            raise DatasetError(f"unknown data setting(s) {', '.join('data.' + k for k in unknown)}; "
                               f"known: {', '.join(sorted(known))}")
        return cls(**{k: v for k, v in values.items() if k in known})

    def n_observed(self, n_coarse: int) -> int:
        """Observed coarse points per trajectory: round(observed_fraction · n_coarse)."""
        return int(round(self.observed_fraction * n_coarse))


def scene_record(scene: Any) -> dict[str, Any]:
    """The scene's spec as a file records it (JSON round trip: tuples become lists)."""
    try:
        return json.loads(json.dumps(scene.spec()))
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"scene spec of {scene!r} is not JSON-serialisable: {exc}") from exc


def generation_attributes(scene: Any, cfg: DatasetConfig) -> dict[str, Any]:
    """The json-able description a file must carry to be reused: format version, scene spec, config."""
    return {"format_version": FORMAT_VERSION, "scene": scene_record(scene), "generation": cfg.record()}


# ---------------------------------------------------------------------------------------------------
# attribute comparison
# ---------------------------------------------------------------------------------------------------
_MISSING = "<missing>"


def _flatten(value: Any, prefix: str) -> dict[str, Any]:
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for k, v in value.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out if out else {prefix: {}}
    return {prefix: value}


def _differences(found: Mapping[str, Any], expected: Mapping[str, Any]) -> list[str]:
    """'key: file X, config Y' for each flattened key whose value differs (keys of either side)."""
    a, b = _flatten(dict(found), ""), _flatten(dict(expected), "")
    return [f"{k}: file {json.dumps(a.get(k, _MISSING))}, config {json.dumps(b.get(k, _MISSING))}"
            for k in sorted(set(a) | set(b)) if a.get(k, _MISSING) != b.get(k, _MISSING)]


def _expected(scene: Any, cfg: Optional[DatasetConfig]) -> dict[str, Any]:
    exp: dict[str, Any] = {"format_version": FORMAT_VERSION}
    if scene is not None:
        exp["scene"] = generation_attributes(scene, cfg or DatasetConfig())["scene"]
    if cfg is not None:
        exp["generation"] = cfg.record()
    return exp


def _mismatch_message(path: Path, diffs: list[str], hint: str = ERROR_HINT) -> str:
    return f"{path}: dataset was generated with different settings ({'; '.join(diffs)}); {hint}"


def _kept_message(path: Path, detail: str) -> str:
    """A file at an explicit path made with other settings: not overwritten; the differences and the fixes."""
    return (f"{path}: the file at this explicitly given data.path was generated with other settings ({detail}; "
            f"'file' = the settings of the run that generated it, 'config' = this run's). A file at an explicit "
            f"data.path is not overwritten with other settings (another run may be using it): give these settings "
            f"another data.path, or set data.path=null (path: null) for one file per setting set under "
            f"data.data_dir, or delete the file to regenerate it")


# ---------------------------------------------------------------------------------------------------
# reading and validation
# ---------------------------------------------------------------------------------------------------
@contextlib.contextmanager
def _open(path: Path) -> Iterator[h5py.File]:
    """Open an existing file read-only; a non-HDF5 or truncated file → DatasetError."""
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise _Damaged(f"{path}: file is corrupt or not an HDF5 file ({exc})") from exc
    try:
        yield f
    except (OSError, RuntimeError, KeyError) as exc:  # read errors inside a damaged file
        raise _Damaged(f"{path}: file is corrupt, reading failed ({exc})") from exc
    finally:
        f.close()


def _read_attributes(f: h5py.File, path: Path) -> dict[str, Any]:
    """Parsed root attrs {format_version, scene, generation, scene_name}; absent ones are None."""
    out: dict[str, Any] = {}
    version = f.attrs.get("format_version")
    try:
        out["format_version"] = int(version) if version is not None and np.ndim(version) == 0 else version
    except (TypeError, ValueError):  # e.g. a string
        out["format_version"] = str(version)
    if isinstance(out["format_version"], np.ndarray):  # json-able, for the messages
        out["format_version"] = out["format_version"].tolist()
    for key, attr in (("scene", "lnf_scene"), ("generation", "lnf_generation")):
        raw = f.attrs.get(attr)
        if raw is None:
            out[key] = None
            continue
        try:
            out[key] = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
        except ValueError as exc:
            raise _Damaged(f"{path}: root attribute {attr} is not valid JSON ({exc})") from exc
    name = f.attrs.get("scene_name")
    out["scene_name"] = name.decode() if isinstance(name, bytes) else name
    return out


def _check_version(path: Path, attrs: Mapping[str, Any]) -> None:
    """load_split's check of the root attribute format_version (ensure_dataset regenerates other versions)."""
    version = attrs.get("format_version")
    if version is None:
        raise DatasetError(f"{path}: root attribute format_version is missing, this lnf reads "
                           f"{FORMAT_VERSION}; {LOAD_HINT}")
    if version != FORMAT_VERSION:
        raise DatasetError(f"{path}: file has format_version {version}, this lnf reads {FORMAT_VERSION}; "
                           f"{LOAD_HINT}")


def _dataset(f: h5py.File, path: Path, key: str) -> h5py.Dataset:
    if key not in f or not isinstance(f[key], h5py.Dataset):
        raise _Damaged(f"{path}: dataset /{key} is missing")
    return f[key]


def _expect_shape(path: Path, key: str, shape: tuple[int, ...], expected: tuple[Any, ...]) -> None:
    """`expected` holds ints or None (any size); len must match."""
    if len(shape) != len(expected) or any(e is not None and s != e for s, e in zip(shape, expected)):
        want = "(" + ", ".join("*" if e is None else str(e) for e in expected) + ")"
        raise _Damaged(f"{path}: dataset /{key} has shape {shape}, expected {want} "
                       f"(inconsistent with the other datasets)")


def _is_arrays_file(f: h5py.File) -> bool:
    """Whether the file was written from a user's arrays (:func:`lnf.trajectories.write_dataset`), not simulated."""
    raw = f.attrs.get("lnf_generation")
    try:
        generation = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw)) if raw is not None else {}
    except ValueError:
        return False
    return isinstance(generation, dict) and generation.get("source") == SOURCE_ARRAYS


def _check_structure(f: h5py.File, path: Path, splits: tuple[str, ...]) -> None:
    """Presence, shapes and dtypes of the shared datasets and of `splits`, and the mask counts (a file written
    from arrays may lack the energies; its optional datasets are checked where present)."""
    arrays = _is_arrays_file(f)
    T = _dataset(f, path, "times").shape
    _expect_shape(path, "times", T, (None,))
    fine = _dataset(f, path, "grids/fine").shape
    _expect_shape(path, "grids/fine", fine, (None, None))
    coarse = _dataset(f, path, "grids/coarse").shape
    _expect_shape(path, "grids/coarse", coarse, (None, fine[1]))
    (T,), (Nf, _), (Nc, _) = T, fine, coarse
    if "grids/weights" in f:
        _expect_shape(path, "grids/weights", _dataset(f, path, "grids/weights").shape, (Nf,))
    for split in splits:
        if split not in f or not isinstance(f[split], h5py.Group):
            raise _Damaged(f"{path}: split group /{split} is missing")
        states = _dataset(f, path, f"{split}/states").shape
        _expect_shape(path, f"{split}/states", states, (None, T, None))
        n = states[0]
        if not arrays or f"{split}/energy" in f:
            _expect_shape(path, f"{split}/energy", _dataset(f, path, f"{split}/energy").shape, (n, T))
        for key in ("kinetic", "potential"):
            if f"{split}/{key}" in f:
                _expect_shape(path, f"{split}/{key}", _dataset(f, path, f"{split}/{key}").shape, (n, T))
        if f"{split}/controls" in f:
            _expect_shape(path, f"{split}/controls", _dataset(f, path, f"{split}/controls").shape, (n, None))
        ff = _dataset(f, path, f"{split}/fields").shape
        _expect_shape(path, f"{split}/fields", ff, (n, T, Nf, None))
        A = ff[3]
        _expect_shape(path, f"{split}/velocities", _dataset(f, path, f"{split}/velocities").shape, (n, T, Nf, A))
        for key in ("coarse_fields", "coarse_velocities"):
            _expect_shape(path, f"{split}/{key}", _dataset(f, path, f"{split}/{key}").shape, (n, T, Nc, A))
        masks_ds = _dataset(f, path, f"{split}/masks")
        _expect_shape(path, f"{split}/masks", masks_ds.shape, (n, Nc))
        if masks_ds.dtype != np.bool_:
            raise _Damaged(f"{path}: dataset /{split}/masks has dtype {masks_ds.dtype}, expected bool")
        counts = masks_ds[...].sum(axis=1)
        if counts.size and (counts.min() != counts.max() or counts.min() < 1):
            raise _Damaged(f"{path}: dataset /{split}/masks must hold the same number (≥ 1) of observed "
                           f"points per trajectory, got counts from {counts.min()} to {counts.max()}")


def dataset_keys(splits: tuple[str, ...] = SPLITS, f: Optional[h5py.File] = None) -> list[str]:
    """Keys of the datasets a file holds (shared ones, then those of `splits`), in the order written; with the
    open file `f`, the optional datasets it holds too (weights, energy parts, controls) and without the energy a
    file written from arrays may lack."""
    keys = ["times", "grids/fine", "grids/coarse"] + [f"{s}/{k}" for s in splits for k in SPLIT_KEYS]
    if f is None:
        return keys
    optional = ["grids/weights"] + [f"{s}/{k}" for s in splits for k in OPTIONAL_SPLIT_KEYS]
    return [k for k in keys if k in f or not (k.endswith("/energy") and _is_arrays_file(f))] + \
        [k for k in optional if k in f]


def _little_endian(data: np.ndarray) -> np.ndarray:
    """`data` as a C-contiguous little-endian array (no copy when it already is one): the bytes hashed."""
    return np.ascontiguousarray(data, dtype=data.dtype.newbyteorder("<"))


def _non_finite(data: np.ndarray) -> tuple[int, int]:
    """(NaN count, inf count) of `data`; (0, 0) for non-float data."""
    if data.dtype.kind not in "fc":
        return 0, 0
    finite = np.isfinite(data)
    if finite.all():
        return 0, 0
    n_nan = int(np.isnan(data).sum())
    return n_nan, int(finite.size - finite.sum()) - n_nan


def _scan(ds: h5py.Dataset) -> tuple[str, int, int]:
    """Checksum and (NaN, inf) counts of `ds`, read in blocks of whole rows (one trajectory of the big
    arrays at a time, ≤ BLOCK_BYTES unless one row is larger) into one reused buffer: bounded memory."""
    if ds.ndim == 0 or ds.shape[0] == 0 or ds.size == 0:
        data = np.asarray(ds[()])
        return _checksum(data), *_non_finite(data)
    h = hashlib.blake2b()
    n, row_shape = ds.shape[0], ds.shape[1:]
    dtype = ds.dtype.newbyteorder("=")
    rows = int(min(n, max(1, BLOCK_BYTES // max(1, int(np.prod(row_shape)) * dtype.itemsize))))
    buffer = np.empty((rows, *row_shape), dtype=dtype)
    n_nan = n_inf = 0
    for start in range(0, n, rows):
        k = min(rows, n - start)
        block = buffer[:k]
        ds.read_direct(block, np.s_[start:start + k], np.s_[0:k])
        h.update(_little_endian(block))
        a, b = _non_finite(block)
        n_nan, n_inf = n_nan + a, n_inf + b
    return f"{CHECKSUM_ALGORITHM}:{h.hexdigest()}", n_nan, n_inf


def _checksum(data: np.ndarray) -> str:
    """The lnf_checksum of an in-memory array."""
    return f"{CHECKSUM_ALGORITHM}:{hashlib.blake2b(_little_endian(np.asarray(data))).hexdigest()}"


def _verify(ds: h5py.Dataset, path: Path, key: str, data: Optional[np.ndarray] = None) -> None:
    """NaN/inf, then the stored checksum of dataset /key (of `data`, its values already read, if given;
    else read block by block); any problem → _Damaged naming the file and /key."""
    if data is None:
        digest, n_nan, n_inf = _scan(ds)
    else:
        digest, (n_nan, n_inf) = _checksum(data), _non_finite(data)
    if n_nan or n_inf:
        raise _Damaged(f"{path}: dataset /{key} contains {n_nan + n_inf} non-finite values "
                       f"({n_nan} NaN, {n_inf} inf); the file is corrupt")
    stored = ds.attrs.get(CHECKSUM_ATTR)
    stored = stored.decode() if isinstance(stored, bytes) else stored
    if stored is None:
        raise _Damaged(f"{path}: dataset /{key} has no {CHECKSUM_ATTR} attribute (expected "
                       f"'{CHECKSUM_ALGORITHM}:<hex>'); the file is corrupt or was not written by lnf")
    if str(stored) != digest:
        raise _Damaged(f"{path}: dataset /{key} does not match its {CHECKSUM_ATTR} (stored {str(stored)[:24]}…, "
                       f"computed {digest[:24]}…): its values changed after it was written; the file is corrupt")


def _verify_all(f: h5py.File, path: Path, splits: tuple[str, ...] = SPLITS) -> None:
    """Checksums and finiteness of every dataset of the shared part and of `splits` (a dataset linked under two
    names, as a file written from arrays links its observation points to its evaluation points, is read once)."""
    seen: set[int] = set()
    for key in dataset_keys(splits, f):
        ds = _dataset(f, path, key)
        if hash(ds.id) in seen:
            continue
        seen.add(hash(ds.id))
        _verify(ds, path, key)


def _read_verified(f: h5py.File, path: Path, key: str) -> np.ndarray:
    """Read dataset /key whole, check it is finite and matches its checksum (→ _Damaged naming /key)."""
    ds = _dataset(f, path, key)
    data = ds[...]
    _verify(ds, path, key, data)
    return data


def _attribute_value(f: h5py.File, name: str) -> Any:
    """Root attribute `name` as a json-able value (the JSON ones parsed), or _MISSING."""
    raw = f.attrs.get(name)
    if raw is None:
        return _MISSING
    raw = raw.decode() if isinstance(raw, bytes) else raw
    raw = raw.tolist() if isinstance(raw, (np.ndarray, np.generic)) else raw
    if name in ("lnf_scene", "lnf_generation") and isinstance(raw, str):
        try:
            return json.loads(raw)
        except ValueError:
            return raw
    return raw


def _attribute_digest(value: Any) -> str:
    """Checksum of one root attribute: BLAKE2b of its canonical JSON (sorted keys, so formatting does not count)."""
    text = json.dumps(value, sort_keys=True, separators=(",", ":"))
    return f"{CHECKSUM_ALGORITHM}:{hashlib.blake2b(text.encode()).hexdigest()}"


def _checksums_attribute(f: h5py.File, path: Path, name: str) -> Optional[dict[str, Any]]:
    """The root attribute `name`, a JSON object of checksums (None when the file has none: an older file);
    anything else → _Damaged naming the file and the attribute."""
    raw = f.attrs.get(name)
    if raw is None:
        return None
    try:
        value = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
        if not isinstance(value, dict):
            raise ValueError("not a JSON object")
    except ValueError as exc:
        raise _Damaged(f"{path}: root attribute {name} is not a JSON object of checksums ({exc}); the file is "
                       f"corrupt") from exc
    return value


def _verify_attributes(f: h5py.File, path: Path) -> None:
    """The root attributes (format_version, lnf_scene, lnf_generation, scene_name) against the checksums stored
    at write time in ``lnf_attributes_checksum``; a file written before that attribute existed is not checked.
    A changed attribute → _Damaged naming the file and the attribute."""
    stored = _checksums_attribute(f, path, ATTRIBUTES_CHECKSUM_ATTR)
    if stored is None:
        return
    for name in ROOT_ATTRIBUTES + tuple(n for n in (MANIFEST_ATTR,) if n in stored):
        digest = _attribute_digest(_attribute_value(f, name))
        if str(stored.get(name)) != digest:
            raise _Damaged(f"{path}: root attribute {name} does not match its checksum in {ATTRIBUTES_CHECKSUM_ATTR} "
                           f"(stored {str(stored.get(name))[:24]}…, computed {digest[:24]}…): it was changed after "
                           f"the file was written (e.g. edited by hand), so the settings it records no longer "
                           f"describe the data")


def _check_generation(f: h5py.File, path: Path, generation: Mapping[str, Any]) -> None:
    """A file written from arrays: the counts, times and observation settings its ``lnf_generation`` records (which
    training trusts) agree with its datasets; → _Damaged naming the file, the attribute key and both values. Holds
    for files of any lnf version (train_times, which the datasets cannot tell, is covered by the attribute
    checksum of newer files)."""
    times = _dataset(f, path, "times")
    n_points = _dataset(f, path, "grids/fine").shape[0]
    found: dict[str, Any] = {"n_times": times.shape[0], "n_points": n_points}
    found.update({f"n_{s}": _dataset(f, path, f"{s}/states").shape[0] for s in SPLITS if f"{s}/states" in f})
    problems = [f"{key} = {json.dumps(generation[key])}, but the file holds {value}" for key, value in found.items()
                if key in generation and generation[key] != value]
    T = times.shape[0]
    train_times = generation.get("train_times")
    if train_times is not None and (isinstance(train_times, bool) or not isinstance(train_times, int)
                                    or not 1 <= train_times <= T):
        problems.append(f"train_times = {json.dumps(train_times)}, but the file holds {T} samples per trajectory "
                        f"(expected an integer in [1, {T}])")
    dt = generation.get("dt")
    if dt is not None and T >= 2:
        step = float(times[1] - times[0])
        if not isinstance(dt, (int, float)) or not math.isclose(float(dt), step, rel_tol=1e-9):
            problems.append(f"dt = {json.dumps(dt)}, but the stored times are {step!r} s apart")
    fraction = generation.get("observed_fraction")
    split = next((s for s in SPLITS if f"{s}/masks" in f and _dataset(f, path, f"{s}/masks").shape[0]), None)
    if isinstance(fraction, (int, float)) and split is not None:
        observed = int(_dataset(f, path, f"{split}/masks")[0].sum())
        if int(round(fraction * n_points)) != observed:
            problems.append(f"observed_fraction = {json.dumps(fraction)} (round({fraction}·{n_points}) points), but "
                            f"each trajectory observes {observed}")
    weights = generation.get("weights")  # what the file was written with must still be there, and nothing else
    if isinstance(weights, bool) and weights != ("grids/weights" in f):
        problems.append(f"weights = {json.dumps(weights)}, but the file "
                        f"{'lacks' if weights else 'holds'} /grids/weights")
    energies = generation.get("energies")
    if energies in ("given", "scene", "none"):
        for key in (f"{s}/{k}" for s in SPLITS for k in ("kinetic", "potential", "energy")):
            if (key in f) != (energies != "none"):
                problems.append(f"energies = {json.dumps(energies)}, but the file "
                                f"{'holds' if key in f else 'lacks'} /{key}")
                break
    if problems:
        raise _Damaged(f"{path}: root attribute lnf_generation disagrees with the data: {'; '.join(problems)} "
                       f"(the attribute or the datasets were changed after the file was written)")


def _check_manifest(f: h5py.File, path: Path, splits: tuple[str, ...] = SPLITS) -> None:
    """The datasets of the shared part and of `splits` are those the file was written with (``lnf_manifest``): each
    one listed is present and carries the checksum listed for its own path (checked against its values by
    :func:`_verify`, so a dataset or group moved, swapped or replaced is found), and none is added. A file written
    before the manifest existed is not checked. Any difference → _Damaged naming the file and the dataset."""
    manifest = _checksums_attribute(f, path, MANIFEST_ATTR)
    if manifest is None:
        return

    def wanted(key: str) -> bool:
        head = key.split("/")[0]
        return head not in SPLITS or head in splits

    for key in sorted(k for k in manifest if wanted(k)):
        if key not in f or not isinstance(f[key], h5py.Dataset):
            raise _Damaged(f"{path}: dataset /{key} is missing, but the file was written with it (its {MANIFEST_ATTR} "
                           f"lists it): it was deleted or moved after the file was written")
        stored = f[key].attrs.get(CHECKSUM_ATTR)
        stored = str(stored.decode() if isinstance(stored, bytes) else stored)
        if stored != str(manifest[key]):
            raise _Damaged(f"{path}: dataset /{key} holds other values than were written there (its {CHECKSUM_ATTR} "
                           f"{stored[:24]}… is not the {str(manifest[key])[:24]}… that {MANIFEST_ATTR} records for "
                           f"/{key}): datasets or groups were moved, swapped or replaced after the file was written")
    for key in dataset_keys(splits, f):
        if key not in manifest:
            raise _Damaged(f"{path}: dataset /{key} was not written with the file (its {MANIFEST_ATTR} does not list "
                           f"it): it was added after the file was written")


def _seal(f: h5py.File) -> None:
    """Record the manifest of a just-written lnf file (every dataset's checksum by its path) and cover it by the
    attribute checksums (:func:`_verify_attributes`)."""
    manifest = {}
    for key in dataset_keys(SPLITS, f):
        value = f[key].attrs.get(CHECKSUM_ATTR)
        manifest[key] = str(value.decode() if isinstance(value, bytes) else value)
    f.attrs[MANIFEST_ATTR] = json.dumps(manifest, sort_keys=True)
    raw = f.attrs[ATTRIBUTES_CHECKSUM_ATTR]
    digests = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
    digests[MANIFEST_ATTR] = _attribute_digest(_attribute_value(f, MANIFEST_ATTR))
    f.attrs[ATTRIBUTES_CHECKSUM_ATTR] = json.dumps(digests)


def content_checksum(path: str | os.PathLike) -> str:
    """A checksum of what the lnf dataset at `path` holds: of its root attributes and of every dataset's checksum,
    keyed by the dataset's path (its values' checksums, not its values: cheap, and exact for a verified file). Two
    files with the same settings but other values, or a file rewritten with other values, differ. DatasetError if
    the file cannot be read."""
    path = Path(path)
    with _open(path) as f:
        record = {"attributes": {name: _attribute_value(f, name) for name in ROOT_ATTRIBUTES}, "datasets": {}}
        for key in dataset_keys(SPLITS, f):
            value = f[key].attrs.get(CHECKSUM_ATTR) if key in f else None
            record["datasets"][key] = str(value.decode() if isinstance(value, bytes) else value)
    text = json.dumps(record, sort_keys=True, separators=(",", ":"), default=str)
    return f"{CHECKSUM_ALGORITHM}:{hashlib.blake2b(text.encode(), digest_size=16).hexdigest()}"


def _points_hint(f: h5py.File) -> str:
    """For a file whose points are stored in float32 (lnf before it stored them in float64): why they may collide."""
    if f["grids/fine"].dtype != np.float32:
        return ""
    return ("; this file stores its points in float32, as lnf.trajectories.write_dataset did before storing "
            "them in float64, which may have merged distinct points: write it again from your simulator's output")


def float32_collisions(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of rows of `points` (N, dim) that are equal in float32 (the precision lnf's model trains in): index
    arrays (a, b) and `same`, True where the pair is equal in float64 too (a point given twice), False where float32
    merges two distinct points. The pairs are neighbours in sorted order, so they connect every group of equal
    points."""
    p64 = np.asarray(points, dtype=np.float64).reshape(len(points), -1)
    p32 = p64.astype(np.float32)
    order = np.lexsort(p32.T[::-1]) if p32.shape[1] else np.arange(len(p32))
    ordered = p32[order]
    hit = np.flatnonzero((ordered[1:] == ordered[:-1]).all(axis=1))
    a, b = order[hit], order[hit + 1]
    return a, b, (p64[a] == p64[b]).all(axis=1)


def check_points(name: str, points: np.ndarray, values: Mapping[str, Any], hint: str = "") -> None:
    """Refuse points the model cannot use as given: two distinct points that float32 makes one, and a point given
    twice with different values in any of `values` (label → (n, T, N, A) array or HDF5 dataset). A point given
    twice with the same values passes. DatasetError naming `name` (the file or argument) and an index pair."""
    p = np.asarray(points, dtype=np.float64)
    a, b, same = float32_collisions(p)
    if not same.all():
        k = int(np.flatnonzero(~same)[0])
        i, j = sorted((int(a[k]), int(b[k])))
        raise DatasetError(
            f"{name}: {int((~same).sum())} pair(s) of distinct points become one point in float32, the precision "
            f"lnf's model trains in, e.g. points {i} and {j}: {p[i].tolist()} and {p[j].tolist()} (both "
            f"{p[i].astype(np.float32).tolist()} in float32); they would be silently merged. Shift and/or scale the "
            f"coordinates (e.g. points - points.mean(axis=0), in a unit in which the body is about 1 across; the "
            f"scene's bounds alike) and write the trajectories again{hint}")
    if not same.any():
        return
    idx = np.unique(np.concatenate([a, b]))  # sorted, unique: the fancy index an HDF5 dataset takes
    ia, ib = np.searchsorted(idx, a), np.searchsorted(idx, b)
    for label, data in values.items():
        sub = np.asarray(data[:, :, idx])
        differ = sub[:, :, ia] != sub[:, :, ib]  # (n, T, pairs, A)
        if differ.any():
            t, k_time, k = (int(x) for x in np.argwhere(differ)[0][:3])
            i, j = sorted((int(a[k]), int(b[k])))
            raise DatasetError(
                f"{name}: points {i} and {j} are the same point {p[i].tolist()}, given twice with different "
                f"{label} (trajectory {t}, sample {k_time}: {sub[t, k_time, ia[k]].tolist()} against "
                f"{sub[t, k_time, ib[k]].tolist()}); {int(differ.any(axis=(0, 1, 3)).sum())} such pair(s). Give each "
                f"point once (drop the duplicates or average their values){hint}")


# ---------------------------------------------------------------------------------------------------
# generation
# ---------------------------------------------------------------------------------------------------
def _grid(scene: Any, resolution: int, kind: str = "centres") -> np.ndarray:
    """The scene's observation points (N, dim_B) float64 at `resolution` (by default its box's midpoint grid;
    `kind` "vertices": its box's vertex grid, see :class:`DatasetConfig`). float64, as stored: a mesh's nodes
    rounded to float32 (0.15 → 0.150000006) can lie outside its cells, where the scene cannot evaluate its field."""
    if kind == "vertices":
        from lnf.scenes.base import Scene

        own = getattr(type(scene), "observation_points", Scene.observation_points)
        if own is not Scene.observation_points:
            raise DatasetError(f"scene {scene.name}: data.coarse_grid=vertices spans the scene's box, but this scene "
                               "gives its own observation points (observation_points); use data.coarse_grid=centres")
        return vertex_grid(resolution, scene.bounds).cpu().numpy().astype(np.float64)
    if hasattr(scene, "observation_points"):
        return np.asarray(scene.observation_points(resolution), dtype=np.float64)
    return midpoint_grid(resolution, scene.bounds).cpu().numpy().astype(np.float64)


def _scene_fields(scene: Any, states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q, q̇ (T, N, A) float32 of states (T, S) at points (N, dim_B), evaluated in float64."""
    q, qdot = scene.fields(states, points.astype(np.float64))
    expected = (states.shape[0], points.shape[0], scene.field_dim)
    for name, arr in (("q", q), ("q̇", qdot)):
        if np.shape(arr) != expected:
            raise DatasetError(f"scene {scene.name}: fields() returned {name} of shape {np.shape(arr)}, "
                               f"expected {expected}")
    return np.asarray(q, dtype=np.float32), np.asarray(qdot, dtype=np.float32)


def _create(group: h5py.Group, name: str, shape: tuple[int, ...], dtype: Any) -> h5py.Dataset:
    """Uncompressed dataset; (n, T, N, A) fields get one chunk per trajectory-time slab."""
    chunks = (1, 1) + shape[2:] if len(shape) == 4 and min(shape) > 0 else None
    return group.create_dataset(name, shape=shape, dtype=dtype, chunks=chunks)


def _write_array(group: h5py.Group, name: str, data: np.ndarray) -> h5py.Dataset:
    """A dataset holding `data`, with its checksum attribute."""
    ds = group.create_dataset(name, data=data)
    ds.attrs[CHECKSUM_ATTR] = _checksum(np.asarray(data, dtype=ds.dtype))
    return ds


SIMULATION_CHUNK = 8  # trajectories per simulate() call of an expensive reference (a step of its progress bar)
GROUND_TRUTH_FOLDER = "ground_truth"  # beside a dataset: lnf.evaluate's simulated references (simulated_ground_truth)
WORKERS_ENV = "LNF_SIMULATION_WORKERS"  # processes that simulate an expensive reference's chunks (default: all cores)

_worker_scene: Any = None  # the scene a forked simulation worker inherits (set just before the pool forks)


def simulation_workers(n_chunks: int) -> int:
    """Processes for `n_chunks` chunks: $LNF_SIMULATION_WORKERS if set (≥ 1), else the cores this process may
    use; 1 where the platform cannot fork."""
    raw = os.environ.get(WORKERS_ENV)
    if raw is None or raw.strip() == "":
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    else:
        try:
            cores = int(raw)
        except ValueError:
            raise DatasetError(f"${WORKERS_ENV}={raw!r}: expected a whole number of processes ≥ 1") from None
        if cores < 1:
            raise DatasetError(f"${WORKERS_ENV}={raw!r}: expected a whole number of processes ≥ 1")
    if "fork" not in multiprocessing.get_all_start_methods():
        return 1
    return max(1, min(cores, n_chunks))


def _start_worker() -> None:
    """Initialiser of a forked simulation worker: one torch thread (the processes share the cores; as in torch's
    own DataLoader workers, a forked process uses no thread pool of its parent)."""
    import torch

    torch.set_num_threads(1)


def _simulate_in_worker(initial: np.ndarray, times: np.ndarray) -> np.ndarray:
    return np.asarray(_worker_scene.simulate(initial, times), dtype=np.float64)


def simulation_chunks(n: int) -> tuple[list[slice], int]:
    """The trajectories 0..n-1 of an expensive reference split into chunks of at most SIMULATION_CHUNK, as evenly
    as the processes of :func:`simulation_workers` share them (16 trajectories on 2 cores: 2 × 8; 8: 2 × 4), and
    the number of processes that simulate them."""
    workers = simulation_workers(max(1, n))
    size = max(1, min(SIMULATION_CHUNK, math.ceil(n / workers)))
    chunks = [slice(i, min(i + size, n)) for i in range(0, n, size)]
    return chunks, min(workers, len(chunks))


def _simulate(scene: Any, initial: np.ndarray, times: np.ndarray, what: str) -> np.ndarray:
    """scene.simulate(initial, times) (n, T, S); where ``scene.expensive_reference``, in the chunks of
    :func:`simulation_chunks` under a progress bar, by :func:`simulation_workers` forked processes at once (each
    chunk is simulated as it would be alone: the same numbers in any number of processes)."""
    global _worker_scene
    if not getattr(scene, "expensive_reference", False):
        return np.asarray(scene.simulate(initial, times), dtype=np.float64)
    slices, workers = simulation_chunks(len(initial))
    if len(slices) <= 1:
        return np.asarray(scene.simulate(initial, times), dtype=np.float64)
    chunks = [initial[s] for s in slices]
    parts: list[Optional[np.ndarray]] = [None] * len(chunks)
    with progress_bar(True, len(initial), f"simulating {what} ({scene.name}, {workers} "
                      f"process{'es' if workers > 1 else ''})", "trajectories") as advance:
        if workers == 1:
            for k, chunk in enumerate(chunks):
                parts[k] = np.asarray(scene.simulate(chunk, times), dtype=np.float64)
                advance(len(chunk))
        else:
            _worker_scene = scene
            try:
                with concurrent.futures.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"),
                                                            initializer=_start_worker) as pool:
                    futures = {pool.submit(_simulate_in_worker, chunk, times): k for k, chunk in enumerate(chunks)}
                    for future in concurrent.futures.as_completed(futures):
                        k = futures[future]
                        parts[k] = future.result()
                        advance(len(chunks[k]))
            except concurrent.futures.process.BrokenProcessPool as err:
                raise DatasetError(f"scene {scene.name}: a simulation worker process died ({err}); set "
                                   f"{WORKERS_ENV}=1 to simulate in this process alone") from err
            finally:
                _worker_scene = None
    return np.concatenate(parts)


def simulated_ground_truth(scene: Any, initial: np.ndarray, times: np.ndarray, folder: Optional[Path]) -> np.ndarray:
    """scene.simulate(initial, times) (n, T, S). Where ``scene.expensive_reference`` and `folder` is given, the
    result is kept there as ``<scene>-<hash>.npy`` (the hash of the scene's spec, the initial states and the times,
    written atomically) and later calls with the same three read it back: the jobs of a sweep that evaluate on the
    same new horizon or initial states simulate the reference once. A cache file that cannot be read, or holds
    another shape or a non-finite value, is simulated again and replaced, with a warning."""
    initial = np.ascontiguousarray(initial, dtype=np.float64)
    times = np.ascontiguousarray(times, dtype=np.float64)
    if folder is None or not getattr(scene, "expensive_reference", False):
        return np.asarray(scene.simulate(initial, times), dtype=np.float64)
    digest = hashlib.blake2b(digest_size=12)
    digest.update(json.dumps(scene_record(scene), sort_keys=True).encode())
    for array in (initial, times):
        digest.update(str(array.shape).encode())
        digest.update(_little_endian(array))
    path = Path(folder) / f"{scene.name}-{digest.hexdigest()}.npy"
    if path.is_file():
        try:
            states = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            log.warning("%s: unreadable (%s); simulating the ground truth again", path, err)
        else:
            if states.ndim == 3 and states.shape[:2] == (len(initial), len(times)) and np.isfinite(states).all():
                log.info("ground truth of %d trajectories × %d samples read from %s", len(initial), len(times), path)
                return states
            log.warning("%s: holds shape %s (or non-finite values), expected (%d, %d, S); simulating the ground "
                        "truth again", path, states.shape, len(initial), len(times))
    states = _simulate(scene, initial, times, "the ground truth")
    buffer = io.BytesIO()
    np.save(buffer, states, allow_pickle=False)
    try:
        write_bytes_atomic(path, buffer.getvalue())
    except OSError as err:  # a cache that cannot be written costs time, not the result
        log.warning("could not keep the ground truth in %s (%s); it will be simulated again next time", path, err)
    return states


def _write_split(group: h5py.Group, scene: Any, initial: np.ndarray, masks: np.ndarray, times: np.ndarray,
                 fine: np.ndarray, coarse: np.ndarray) -> None:
    """Simulate `initial` (n, S) over `times` and write one split, trajectory by trajectory, hashing each
    (n, T, N, A) field array as it is written. A scene whose reference is expensive (an FEM model) is simulated a
    few trajectories at a time, under a progress bar."""
    states = _simulate(scene, initial, times, f"the {group.name.strip('/')} split")
    n, T = len(initial), len(times)
    if states.ndim != 3 or states.shape[:2] != (n, T):
        raise DatasetError(f"scene {scene.name}: simulate() returned shape {states.shape}, expected ({n}, {T}, S)")
    if not np.isfinite(states).all():
        raise DatasetError(f"scene {scene.name}: simulate() returned {int((~np.isfinite(states)).sum())} "
                           f"non-finite state values for split {group.name}")
    _write_array(group, "states", states)
    _write_array(group, "energy", np.asarray(scene.true_energy(states), dtype=np.float64))
    _write_array(group, "masks", masks)
    A = scene.field_dim
    out = {key: _create(group, key, (n, T, len(pts), A), np.float32)
           for key, pts in zip(FIELD_KEYS, (fine, fine, coarse, coarse))}
    hashes = {key: hashlib.blake2b() for key in FIELD_KEYS}
    for i in range(n):
        values = (*_scene_fields(scene, states[i], fine), *_scene_fields(scene, states[i], coarse))
        for key, value in zip(FIELD_KEYS, values):
            out[key][i] = value
            hashes[key].update(_little_endian(value))
    for key in FIELD_KEYS:
        out[key].attrs[CHECKSUM_ATTR] = f"{CHECKSUM_ALGORITHM}:{hashes[key].hexdigest()}"


def _draw(scene: Any, cfg: DatasetConfig, n_coarse: int) -> tuple[np.ndarray, np.ndarray]:
    """All initial states (n_total, S), then all masks (n_total, Nc) bool, from one seeded rng."""
    rng = np.random.default_rng(cfg.seed)
    n_total = cfg.n_train + cfg.n_val + cfg.n_test
    initial = np.asarray(scene.sample_initial_states(n_total, rng), dtype=np.float64)
    n_obs = cfg.n_observed(n_coarse)
    if n_obs < 1:
        raise DatasetError(f"data.observed_fraction = {cfg.observed_fraction} observes 0 of the {n_coarse} "
                           f"coarse points; raise data.observed_fraction or data.coarse_resolution")
    masks = np.zeros((n_total, n_coarse), dtype=bool)
    for i in range(n_total):
        masks[i, rng.permutation(n_coarse)[:n_obs]] = True
    return initial, masks


def _remove_stale_temporaries(path: Path) -> None:
    """Delete temporaries of `path` left by killed writers on this host (SIGKILL runs no cleanup).

    A temporary is named ``{name}.tmp-{host}-{pid}``; it is stale when that process no longer exists.
    Temporaries of other hosts (a shared file system) are left alone.
    """
    prefix = f"{path.name}.tmp-{socket.gethostname()}-"
    for tmp in path.parent.glob(glob_escape(prefix) + "*"):
        pid = tmp.name[len(prefix):]
        if writer_is_gone(pid):
            log.warning("removing %s, left by an interrupted generation (process %s is gone)", tmp, pid)
            tmp.unlink(missing_ok=True)


def _needed_bytes(n: int, T: int, S: int, Nf: int, Nc: int, dim: int, A: int) -> int:
    """An upper bound of the file's size: the arrays' bytes (n trajectories, T samples, S state entries,
    Nf/Nc points in dim_B = `dim`, A field components) + 1 %, 128 bytes of index per field chunk (HDF5 needs
    ~70), and 1 MiB of metadata."""
    data = T * 8 + (Nf + Nc) * dim * 8 + n * (T * S * 8 + T * 8 + Nc + 2 * T * (Nf + Nc) * A * 4)
    return int(data * 1.01) + 128 * (4 * n * T) + (1 << 20)


def _size(n_bytes: float) -> str:
    """Bytes in MB (GB from 1 GB on), decimal units."""
    return f"{n_bytes / 1e9:.2f} GB" if n_bytes >= 1e9 else f"{n_bytes / 1e6:.1f} MB"


def _free_bytes(directory: Path) -> Optional[int]:
    """Free space on the file system of `directory` (None if it cannot be read)."""
    try:
        return int(shutil.disk_usage(directory).free)
    except OSError:
        return None


def _check_free_space(path: Path, needed: int) -> None:
    """DatasetError naming the file, the space needed and the space free, if the disk cannot hold it."""
    free = _free_bytes(path.parent)
    if free is not None and free < needed:
        raise DatasetError(f"{path}: not enough free disk space to generate the dataset: it needs about "
                           f"{_size(needed)}, {path.parent} has {_size(free)} free; free some space or point "
                           f"data.path (or data.data_dir) at another disk")


def _preallocate(tmp: Path, needed: int) -> None:
    """Reserve `needed` bytes for the (just created, still closed) HDF5 file `tmp`, so that a disk filling
    up meanwhile fails here with an OSError, not inside HDF5, whose failed writes can crash the process.
    HDF5, which reopens the file, truncates it to its contents on close. A file system that cannot
    preallocate is skipped; ENOSPC, EDQUOT and EFBIG are raised."""
    if not hasattr(os, "posix_fallocate"):
        return
    fd = os.open(tmp, os.O_RDWR)
    try:
        os.posix_fallocate(fd, 0, needed)
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            raise
        log.debug("cannot preallocate %s (%s); writing without a reservation", tmp, exc)
    finally:
        os.close(fd)


def _abandon(f: Optional[h5py.File]) -> None:
    """Close `f` after a failed write, ignoring the errors of flushing what could not be written."""
    if f is None:
        return
    try:
        f.close()
    except Exception as exc:  # noqa: BLE001 - the write already failed; this only releases the handle
        log.debug("closing a failed dataset file raised %r", exc)


def _is_write_failure(exc: BaseException) -> bool:
    """An OSError, or an error raised inside h5py (a failed flush raises RuntimeError), not the scene's."""
    if isinstance(exc, OSError):
        return True
    if not isinstance(exc, RuntimeError) or exc.__traceback__ is None:
        return False
    tb = exc.__traceback__
    while tb.tb_next is not None:
        tb = tb.tb_next
    return f"{os.sep}h5py{os.sep}" in tb.tb_frame.f_code.co_filename or \
        tb.tb_frame.f_code.co_filename.startswith("h5py")


def _write_failed_message(path: Path, needed: int, exc: BaseException) -> str:
    free = _free_bytes(path.parent)
    where = f"{path.parent} has {_size(free)} free now" if free is not None else f"on {path.parent}"
    reason = str((exc.strerror if isinstance(exc, OSError) else None) or exc).split("\n")[0].strip()
    return (f"{path}: writing the dataset failed ({reason}); it needs about {_size(needed)} of disk "
            f"space ({where}); nothing was written to {path.name} (the temporary was removed); free some space "
            f"or point data.path (or data.data_dir) at another disk")


def generate_dataset(scene: Any, cfg: DatasetConfig, path: str | os.PathLike) -> Path:
    """Simulate and write the dataset of `scene` under `cfg` to `path` atomically; returns the path.

    Not enough free space → DatasetError before any temporary is made; an OSError while writing (a full disk),
    or an h5py error, → DatasetError naming the file and the space needed, with the temporary removed (a file
    already at `path` stays as it was). Other errors (the scene's) propagate, also without a temporary."""
    path = Path(path)
    attrs = generation_attributes(scene, cfg)
    times = cfg.dt * np.arange(cfg.n_times, dtype=np.float64)
    fine, coarse = _grid(scene, cfg.fine_resolution), _grid(scene, cfg.coarse_resolution, cfg.coarse_grid)
    initial, masks = _draw(scene, cfg, len(coarse))
    bounds = np.cumsum([0, cfg.n_train, cfg.n_val, cfg.n_test])
    needed = _needed_bytes(int(bounds[-1]), cfg.n_times, int(np.prod(initial.shape[1:])), len(fine), len(coarse),
                           fine.shape[1], int(scene.field_dim))
    log.info("generating %s dataset at %s (%d trajectories × %d samples, ≤ %s)", scene.name, path, bounds[-1],
             cfg.n_times, _size(needed))
    with atomic_h5(path, needed) as f:
        write_root_attributes(f, attrs["scene"], attrs["generation"], str(scene.name))
        _write_array(f, "times", times)
        _write_array(f, "grids/fine", fine)
        _write_array(f, "grids/coarse", coarse)
        for k, split in enumerate(SPLITS):
            sl = slice(bounds[k], bounds[k + 1])
            _write_split(f.create_group(split), scene, initial[sl], masks[sl], times, fine, coarse)
    return path


def write_root_attributes(f: h5py.File, scene_spec: Optional[dict], generation: dict, scene_name: str) -> None:
    """The root attributes every lnf dataset carries (format version, scene spec, generation settings, name), and
    the checksum of each (``lnf_attributes_checksum``), which verification compares: an edited attribute is found."""
    f.attrs["format_version"] = FORMAT_VERSION
    f.attrs["lnf_scene"] = json.dumps(scene_spec)
    f.attrs["lnf_generation"] = json.dumps(generation)
    f.attrs["scene_name"] = scene_name
    f.attrs[ATTRIBUTES_CHECKSUM_ATTR] = json.dumps({name: _attribute_digest(_attribute_value(f, name))
                                                    for name in ROOT_ATTRIBUTES})


@contextlib.contextmanager
def atomic_h5(path: Path, needed: int) -> Iterator[h5py.File]:
    """An HDF5 file open for writing at a temporary name beside `path`, renamed onto `path` when the block ends.

    Free space for `needed` bytes is checked before anything is created and reserved (posix_fallocate); any failure
    removes the temporary, so a file at `path` is either the old one or the complete new one. An OSError or h5py
    error while writing → DatasetError naming the file and the space needed; other errors propagate."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temporaries(path)
    _check_free_space(path, needed)
    tmp = path.with_name(f"{path.name}.tmp-{socket.gethostname()}-{os.getpid()}")
    f: Optional[h5py.File] = None
    try:
        h5py.File(tmp, "w").close()
        _preallocate(tmp, needed)
        f = h5py.File(tmp, "r+")
        yield f
        if ATTRIBUTES_CHECKSUM_ATTR in f.attrs:  # an lnf dataset (write_root_attributes): record what it holds
            _seal(f)
        f.close()  # flushes: may fail too
        f = None
        os.replace(tmp, path)
    except BaseException as exc:
        _abandon(f)
        tmp.unlink(missing_ok=True)
        if _is_write_failure(exc):
            raise DatasetError(_write_failed_message(path, needed, exc)) from exc
        raise


# ---------------------------------------------------------------------------------------------------
# reuse
# ---------------------------------------------------------------------------------------------------
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


# ---------------------------------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------------------------------
def observed_index(masks: np.ndarray) -> np.ndarray:
    """Each trajectory's observed coarse points as sorted indices (n, Nobs), from its masks (n, Nc) bool."""
    return np.stack([np.flatnonzero(m) for m in masks])


@dataclass
class TrajectorySplit:
    """One split of a dataset, in memory. n trajectories, T samples, Nf fine / Nc coarse points.

    times (T,) [s]; fine_points (Nf, dim_B), coarse_points (Nc, dim_B) as stored (float64; float32 in older
    files); states (n, T, S);
    energy (n, T); fields, velocities (n, T, Nf, A) float32; coarse_fields, coarse_velocities
    (n, T, Nc, A) float32; masks (n, Nc) bool; attrs: parsed root attributes.
    """

    times: np.ndarray
    fine_points: np.ndarray
    coarse_points: np.ndarray
    states: np.ndarray
    energy: np.ndarray
    fields: np.ndarray
    velocities: np.ndarray
    coarse_fields: np.ndarray
    coarse_velocities: np.ndarray
    masks: np.ndarray
    attrs: dict
    kinetic: Optional[np.ndarray] = None  # (n, T) stored energy parts (files written from arrays)
    potential: Optional[np.ndarray] = None
    controls: Optional[np.ndarray] = None  # (n, c) stored per-trajectory loads (files written from arrays)
    weights: Optional[np.ndarray] = None  # (Nf,) quadrature weights of the fine points, when the file has them

    def __len__(self) -> int:
        return self.states.shape[0]

    @property
    def from_arrays(self) -> bool:
        """Whether the split was written from a user's arrays (no simulator behind it)."""
        return (self.attrs.get("generation") or {}).get("source") == SOURCE_ARRAYS

    def energy_parts(self, scene: Any = None) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """The reference (kinetic, potential) energies (n, T) each: stored ones, else from the states through
        ``scene.true_energy_parts``; None when neither exists (a file written from arrays without energies)."""
        if self.kinetic is not None and self.potential is not None:
            return self.kinetic, self.potential
        if scene is not None and self.states.shape[-1] > 0 and scene.provides("true_energy_parts"):
            return scene.true_energy_parts(self.states)
        return None

    @property
    def train_times(self) -> int:
        """Number of leading samples used for training (from the generation attributes)."""
        return int(self.attrs["generation"]["train_times"])

    def observed(self, max_time: int | None = None, velocities: bool = False) -> tuple[np.ndarray, ...]:
        """Each trajectory's masked coarse observations over its first `max_time` samples (all if None).

        Returns points (n, Nobs, dim_B) (as stored) and values (n, T', Nobs, A) float32, and with
        `velocities` also the velocity fields (n, T', Nobs, A) at the same points.
        """
        T = self.times.shape[0]
        t = T if max_time is None else int(max_time)
        if not 1 <= t <= T:
            raise DatasetError(f"max_time must be in [1, {T}], got {max_time!r}")
        idx = observed_index(self.masks)
        points = self.coarse_points[idx]
        values = np.take_along_axis(self.coarse_fields[:, :t], idx[:, None, :, None], axis=2)
        if not velocities:
            return points, values
        return points, values, np.take_along_axis(self.coarse_velocities[:, :t], idx[:, None, :, None], axis=2)


def load_split(path: str | os.PathLike, split: str, scene: Any = None,
               cfg: Optional[DatasetConfig] = None) -> TrajectorySplit:
    """Load and validate one split (structure, checksums, finiteness of what it reads); with `scene`/`cfg`,
    also check the file was generated from them."""
    path = Path(path)
    if split not in SPLITS:
        raise DatasetError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    if not path.is_file():
        raise DatasetError(f"{path}: dataset file not found; run `python -m lnf.train` (it generates the dataset) "
                           f"or call lnf.dataset.ensure_dataset(scene, cfg, path)")
    attrs: dict[str, Any] = {}
    try:
        with _open(path) as f:
            attrs = _read_attributes(f, path)
            _check_version(path, attrs)
            _verify_attributes(f, path)
            if (attrs.get("generation") or {}).get("source") == SOURCE_ARRAYS:
                if scene is not None:
                    check_scene_fits(path, f, attrs, scene)
            elif scene is not None or cfg is not None:
                exp = _expected(scene, cfg)
                diffs = _differences({k: attrs.get(k) for k in exp}, exp)
                if diffs:
                    raise DatasetError(_mismatch_message(path, diffs, "load it with the settings it was made "
                                                                      "with, or regenerate it with these with "
                                                                      "lnf.dataset.ensure_dataset"))
            _check_structure(f, path, (split,))
            arrays = (attrs.get("generation") or {}).get("source") == SOURCE_ARRAYS
            if arrays:
                _check_generation(f, path, attrs["generation"])
            data = {name: _read_verified(f, path, key) for name, key in (
                ("times", "times"), ("fine_points", "grids/fine"), ("coarse_points", "grids/coarse"),
                ("states", f"{split}/states"), ("energy", f"{split}/energy"), ("fields", f"{split}/fields"),
                ("velocities", f"{split}/velocities"), ("coarse_fields", f"{split}/coarse_fields"),
                ("coarse_velocities", f"{split}/coarse_velocities"), ("masks", f"{split}/masks"))
                if key in f or not key.endswith("/energy")}
            data.update({name: _read_verified(f, path, key) for name, key in (
                ("kinetic", f"{split}/kinetic"), ("potential", f"{split}/potential"),
                ("controls", f"{split}/controls"), ("weights", "grids/weights")) if key in f})
            if "energy" not in data:  # a file written from arrays without energies
                data["energy"] = None
            _check_manifest(f, path, (split,))  # the split's datasets are the ones written there, none deleted
            if arrays:  # points stored in float64: refused where float32 (the model's) would merge them
                check_points(f"{path}: /grids/fine", data["fine_points"], {
                    f"/{split}/fields": data["fields"], f"/{split}/velocities": data["velocities"]},
                    _points_hint(f))
    except _Damaged as exc:
        hint = ARRAYS_HINT if (attrs.get("generation") or {}).get("source") == SOURCE_ARRAYS else LOAD_HINT
        raise DatasetError(f"{exc}; {hint}") from exc
    return TrajectorySplit(attrs=attrs, **data)


def dataset_source(path: str | os.PathLike) -> Optional[str]:
    """``"arrays"`` for a file written from a user's arrays (:func:`lnf.trajectories.write_dataset`), ``"simulation"``
    for one generated from a scene's simulator, None when there is no readable file at `path`."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        with h5py.File(path, "r") as f:
            return SOURCE_ARRAYS if _is_arrays_file(f) else "simulation"
    except OSError:
        return None


def stored_generation(path: str | os.PathLike) -> dict[str, Any]:
    """The generation settings a file records (``lnf_generation``): for a file written from arrays, its counts,
    times and observation settings, which training takes from the file instead of ``data.*``. Checked against the
    attribute checksums the file carries (an edited attribute → DatasetError naming the file and the attribute)."""
    path = Path(path)
    with _open(path) as f:
        generation = _read_attributes(f, path).get("generation")
        try:
            _verify_attributes(f, path)
        except _Damaged as exc:
            arrays = isinstance(generation, dict) and generation.get("source") == SOURCE_ARRAYS
            raise DatasetError(f"{exc}; {ARRAYS_HINT if arrays else LOAD_HINT}") from exc
    if not isinstance(generation, dict):
        raise DatasetError(f"{path}: root attribute lnf_generation is missing; the file was not written by lnf")
    return generation


def check_scene_fits(path: Path, f: h5py.File, attrs: Mapping[str, Any], scene: Any) -> None:
    """A file written from arrays fits `scene` when the scene it records (if any) is `scene` and its points and
    fields have the scene's body dimension and field components; else DatasetError naming what differs."""
    recorded = attrs.get("scene")
    if recorded is not None:
        diffs = _differences({"scene": recorded}, {"scene": scene_record(scene)})
        if diffs:
            raise DatasetError(f"{path}: the trajectories were written for another scene ({'; '.join(diffs)}; "
                               f"'file' = the scene given to lnf.trajectories.write_dataset, 'config' = this run's). "
                               f"Train with the scene they were written for, or write them again with this scene "
                               f"(or with scene=None, which lets any scene of the same dimensions train on them)")
    dim_b = _dataset(f, path, "grids/fine").shape[1]
    if dim_b != scene.body_dim:
        raise DatasetError(f"{path}: the points have {dim_b} coordinates (dim_B), but scene {scene.name!r} has a "
                           f"{scene.body_dim}-D body (scene.bounds = {scene.bounds})")
    first = next((s for s in SPLITS if f"{s}/fields" in f), None)
    n_comp = _dataset(f, path, f"{first}/fields").shape[-1] if first else scene.field_dim
    if n_comp != scene.field_dim:
        raise DatasetError(f"{path}: the fields have {n_comp} components, but scene {scene.name!r} has "
                           f"field_dim = {scene.field_dim}")


def verify_dataset(path: str | os.PathLike, scene: Any = None) -> Path:
    """Check a file written from arrays before training on it (it cannot be regenerated): complete, intact (every
    checksum, no NaN/inf) and fitting `scene`; DatasetError naming the file, the key and what to do otherwise."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: dataset file not found; write your trajectories there with "
                           f"lnf.trajectories.write_dataset (see docs/own_system.md)")
    try:
        with _open(path) as f:
            attrs = _read_attributes(f, path)
            _check_version(path, attrs)
            _verify_attributes(f, path)
            if scene is not None:
                check_scene_fits(path, f, attrs, scene)
            _check_structure(f, path, SPLITS)
            if _is_arrays_file(f):
                _check_generation(f, path, attrs["generation"])
            _verify_all(f, path, SPLITS)
            _check_manifest(f, path, SPLITS)
            if _is_arrays_file(f):
                check_points(f"{path}: /grids/fine", f["grids/fine"][...], {
                    f"/{s}/{key}": f[f"{s}/{key}"] for s in SPLITS for key in ("fields", "velocities")},
                    _points_hint(f))
    except _Damaged as exc:
        raise DatasetError(f"{exc}; {ARRAYS_HINT}") from exc
    log.info("verified dataset %s (written from arrays)", path)
    return path
