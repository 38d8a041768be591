"""Generating a dataset: simulation of the splits, sampling on the grids, and the atomic HDF5 write."""
from __future__ import annotations

import concurrent.futures
import contextlib
import errno
import hashlib
import io
import json
import math
import multiprocessing
import os
import shutil
import socket
from glob import escape as glob_escape
from pathlib import Path
from typing import Any, Iterator, Optional

import h5py
import numpy as np

from lnf.progress import progress_bar
from lnf.quadrature import midpoint_grid, vertex_grid
from lnf.tempfiles import write_bytes_atomic, writer_is_gone
from lnf.dataset.config import DatasetConfig, generation_attributes, scene_record
from lnf.dataset.format import (
    ATTRIBUTES_CHECKSUM_ATTR, CHECKSUM_ALGORITHM, CHECKSUM_ATTR, DatasetError, FIELD_KEYS, FORMAT_VERSION,
    ROOT_ATTRIBUTES, SPLITS, log)
from lnf.dataset.verify import _attribute_digest, _attribute_value, _checksum, _little_endian, _seal


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


