"""Reading and validating a dataset file: structure, shapes, checksums, finiteness, attributes, points."""
from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any, Iterator, Mapping, Optional

import h5py
import numpy as np

from lnf.dataset.config import _MISSING
from lnf.dataset.format import (
    ATTRIBUTES_CHECKSUM_ATTR, BLOCK_BYTES, CHECKSUM_ALGORITHM, CHECKSUM_ATTR, DatasetError, FORMAT_VERSION,
    LOAD_HINT, MANIFEST_ATTR, OPTIONAL_SPLIT_KEYS, ROOT_ATTRIBUTES, SOURCE_ARRAYS, SPLITS, SPLIT_KEYS, _Damaged)


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


