"""Ground-truth trajectory datasets in HDF5 (DESIGN.md §5): generation, reuse checks, loading.

A dataset file holds, for the splits ``train``/``val``/``test`` (disjoint trajectories), the full-order
states, their energies, and the configuration and velocity fields sampled on a fine evaluation grid and
on a coarse observation grid, plus each trajectory's fixed random mask of observed coarse points.

Layout (``FORMAT_VERSION`` 1)::

    attrs: format_version (int), lnf_scene (json of scene.spec()), lnf_generation (json of the
           DatasetConfig), scene_name (str)
    /times                       (T,)            float64  [s], t_k = dt·k
    /grids/fine                  (Nf, dim_B)     float32  midpoint grid, fine_resolution per axis
    /grids/coarse                (Nc, dim_B)     float32  midpoint grid, coarse_resolution per axis
    /{split}/states              (n, T, S)       float64
    /{split}/energy              (n, T)          float64  scene.true_energy
    /{split}/fields              (n, T, Nf, A)   float32  q on the fine grid
    /{split}/velocities          (n, T, Nf, A)   float32  q̇ on the fine grid
    /{split}/coarse_fields       (n, T, Nc, A)   float32
    /{split}/coarse_velocities   (n, T, Nc, A)   float32
    /{split}/masks               (n, Nc)         bool     exactly round(observed_fraction·Nc) True per row

Files are written atomically (temporary file, then ``os.replace``), so a file at the target path is
always complete; a temporary left by a killed writer is removed by the next generation of that file.
Every user-facing failure raises :class:`DatasetError` naming the file and the key.
"""
from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import socket
from dataclasses import asdict, dataclass, fields as dataclass_fields
from glob import escape as glob_escape
from pathlib import Path
from typing import Any, Iterator, Mapping, Optional

import h5py
import numpy as np

from lnf.quadrature import midpoint_grid

FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")
FIX_HINT = "delete the file or set data.on_mismatch=regenerate to regenerate it"

log = logging.getLogger("lnf.dataset")


class DatasetError(ValueError):
    """A dataset file or dataset setting is unusable; the message names the file/key and the fix."""


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
        train_times: the first samples used for training (time split; DESIGN.md §5).
        fine_resolution: evaluation grid, fine_resolution^dim_B cell centres.
        coarse_resolution: observation grid, coarse_resolution^dim_B cell centres.
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


def generation_attributes(scene: Any, cfg: DatasetConfig) -> dict[str, Any]:
    """The json-able description a file must carry to be reused: format version, scene spec, config."""
    try:
        spec = json.loads(json.dumps(scene.spec()))
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"scene spec of {scene!r} is not JSON-serialisable: {exc}") from exc
    return {"format_version": FORMAT_VERSION, "scene": spec, "generation": asdict(cfg)}


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
        exp["generation"] = asdict(cfg)
    return exp


def _mismatch_message(path: Path, diffs: list[str]) -> str:
    return (f"{path}: dataset was generated with different settings ({'; '.join(diffs)}); "
            f"{FIX_HINT}")


# ---------------------------------------------------------------------------------------------------
# reading and validation
# ---------------------------------------------------------------------------------------------------
@contextlib.contextmanager
def _open(path: Path) -> Iterator[h5py.File]:
    """Open an existing file read-only; a non-HDF5 or truncated file → DatasetError."""
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise DatasetError(f"{path}: file is corrupt or not an HDF5 file ({exc}); {FIX_HINT}") from exc
    try:
        yield f
    except (OSError, RuntimeError, KeyError) as exc:  # read errors inside a damaged file
        raise DatasetError(f"{path}: file is corrupt, reading failed ({exc}); {FIX_HINT}") from exc
    finally:
        f.close()


def _read_attributes(f: h5py.File, path: Path) -> dict[str, Any]:
    """Parsed root attrs {format_version, scene, generation, scene_name}; absent ones are None."""
    out: dict[str, Any] = {}
    version = f.attrs.get("format_version")
    out["format_version"] = int(version) if version is not None and np.ndim(version) == 0 else version
    for key, attr in (("scene", "lnf_scene"), ("generation", "lnf_generation")):
        raw = f.attrs.get(attr)
        if raw is None:
            out[key] = None
            continue
        try:
            out[key] = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
        except ValueError as exc:
            raise DatasetError(f"{path}: root attribute {attr} is not valid JSON ({exc}); {FIX_HINT}") from exc
    name = f.attrs.get("scene_name")
    out["scene_name"] = name.decode() if isinstance(name, bytes) else name
    return out


def _check_version(path: Path, attrs: Mapping[str, Any]) -> None:
    version = attrs.get("format_version")
    if version is None:
        raise DatasetError(f"{path}: root attribute format_version is missing, this lnf reads "
                           f"{FORMAT_VERSION}; regenerate it ({FIX_HINT})")
    if version != FORMAT_VERSION:
        raise DatasetError(f"{path}: file has format_version {version}, this lnf reads {FORMAT_VERSION}; "
                           f"regenerate it ({FIX_HINT})")


def _dataset(f: h5py.File, path: Path, key: str) -> h5py.Dataset:
    if key not in f or not isinstance(f[key], h5py.Dataset):
        raise DatasetError(f"{path}: dataset /{key} is missing; {FIX_HINT}")
    return f[key]


def _expect_shape(path: Path, key: str, shape: tuple[int, ...], expected: tuple[Any, ...]) -> None:
    """`expected` holds ints or None (any size); len must match."""
    if len(shape) != len(expected) or any(e is not None and s != e for s, e in zip(shape, expected)):
        want = "(" + ", ".join("*" if e is None else str(e) for e in expected) + ")"
        raise DatasetError(f"{path}: dataset /{key} has shape {shape}, expected {want} "
                           f"(inconsistent with the other datasets); {FIX_HINT}")


def _check_structure(f: h5py.File, path: Path, splits: tuple[str, ...]) -> None:
    """Presence, shapes and dtypes of the shared datasets and of `splits`, and the mask counts."""
    T = _dataset(f, path, "times").shape
    _expect_shape(path, "times", T, (None,))
    fine = _dataset(f, path, "grids/fine").shape
    _expect_shape(path, "grids/fine", fine, (None, None))
    coarse = _dataset(f, path, "grids/coarse").shape
    _expect_shape(path, "grids/coarse", coarse, (None, fine[1]))
    (T,), (Nf, _), (Nc, _) = T, fine, coarse
    for split in splits:
        if split not in f or not isinstance(f[split], h5py.Group):
            raise DatasetError(f"{path}: split group /{split} is missing; {FIX_HINT}")
        states = _dataset(f, path, f"{split}/states").shape
        _expect_shape(path, f"{split}/states", states, (None, T, None))
        n = states[0]
        _expect_shape(path, f"{split}/energy", _dataset(f, path, f"{split}/energy").shape, (n, T))
        ff = _dataset(f, path, f"{split}/fields").shape
        _expect_shape(path, f"{split}/fields", ff, (n, T, Nf, None))
        A = ff[3]
        _expect_shape(path, f"{split}/velocities", _dataset(f, path, f"{split}/velocities").shape, (n, T, Nf, A))
        for key in ("coarse_fields", "coarse_velocities"):
            _expect_shape(path, f"{split}/{key}", _dataset(f, path, f"{split}/{key}").shape, (n, T, Nc, A))
        masks_ds = _dataset(f, path, f"{split}/masks")
        _expect_shape(path, f"{split}/masks", masks_ds.shape, (n, Nc))
        if masks_ds.dtype != np.bool_:
            raise DatasetError(f"{path}: dataset /{split}/masks has dtype {masks_ds.dtype}, expected bool; {FIX_HINT}")
        counts = masks_ds[...].sum(axis=1)
        if counts.size and (counts.min() != counts.max() or counts.min() < 1):
            raise DatasetError(f"{path}: dataset /{split}/masks must hold the same number (≥ 1) of observed "
                               f"points per trajectory, got counts from {counts.min()} to {counts.max()}; {FIX_HINT}")


def _read_finite(f: h5py.File, path: Path, key: str) -> np.ndarray:
    """Read a float dataset; any NaN or inf → DatasetError naming /key and the count."""
    data = _dataset(f, path, key)[...]
    bad = ~np.isfinite(data)
    if bad.any():
        n_nan = int(np.isnan(data).sum())
        raise DatasetError(f"{path}: dataset /{key} contains {int(bad.sum())} non-finite values "
                           f"({n_nan} NaN, {int(bad.sum()) - n_nan} inf); the file is damaged: delete it to regenerate it")
    return data


# ---------------------------------------------------------------------------------------------------
# generation
# ---------------------------------------------------------------------------------------------------
def _grid(scene: Any, resolution: int) -> np.ndarray:
    """Midpoint grid (N, dim_B) float32 on the scene's body."""
    return midpoint_grid(resolution, scene.bounds).cpu().numpy().astype(np.float32)


def _scene_fields(scene: Any, states: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """q, q̇ (T, N, A) float32 of states (T, S) at float32 points (N, dim_B), evaluated in float64."""
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


def _write_split(group: h5py.Group, scene: Any, initial: np.ndarray, masks: np.ndarray, times: np.ndarray,
                 fine: np.ndarray, coarse: np.ndarray) -> None:
    """Simulate `initial` (n, S) over `times` and write one split, trajectory by trajectory."""
    states = np.asarray(scene.simulate(initial, times), dtype=np.float64)
    n, T = len(initial), len(times)
    if states.ndim != 3 or states.shape[:2] != (n, T):
        raise DatasetError(f"scene {scene.name}: simulate() returned shape {states.shape}, expected ({n}, {T}, S)")
    if not np.isfinite(states).all():
        raise DatasetError(f"scene {scene.name}: simulate() returned {int((~np.isfinite(states)).sum())} "
                           f"non-finite state values for split {group.name}")
    group.create_dataset("states", data=states)
    group.create_dataset("energy", data=np.asarray(scene.true_energy(states), dtype=np.float64))
    group.create_dataset("masks", data=masks)
    A = scene.field_dim
    out = {key: _create(group, key, (n, T, len(pts), A), np.float32)
           for key, pts in (("fields", fine), ("velocities", fine),
                            ("coarse_fields", coarse), ("coarse_velocities", coarse))}
    for i in range(n):
        out["fields"][i], out["velocities"][i] = _scene_fields(scene, states[i], fine)
        out["coarse_fields"][i], out["coarse_velocities"][i] = _scene_fields(scene, states[i], coarse)


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
        if not pid.isdigit():
            continue
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            log.warning("removing %s, left by an interrupted generation (process %s is gone)", tmp, pid)
            tmp.unlink(missing_ok=True)
        except PermissionError:  # alive, another user's
            pass


def generate_dataset(scene: Any, cfg: DatasetConfig, path: str | os.PathLike) -> Path:
    """Simulate and write the dataset of `scene` under `cfg` to `path` atomically; returns the path."""
    path = Path(path)
    attrs = generation_attributes(scene, cfg)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temporaries(path)
    tmp = path.with_name(f"{path.name}.tmp-{socket.gethostname()}-{os.getpid()}")
    times = cfg.dt * np.arange(cfg.n_times, dtype=np.float64)
    fine, coarse = _grid(scene, cfg.fine_resolution), _grid(scene, cfg.coarse_resolution)
    initial, masks = _draw(scene, cfg, len(coarse))
    bounds = np.cumsum([0, cfg.n_train, cfg.n_val, cfg.n_test])
    log.info("generating %s dataset at %s (%d trajectories × %d samples)", scene.name, path, bounds[-1], cfg.n_times)
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["lnf_scene"] = json.dumps(attrs["scene"])
            f.attrs["lnf_generation"] = json.dumps(attrs["generation"])
            f.attrs["scene_name"] = str(scene.name)
            f.create_dataset("times", data=times)
            f.create_dataset("grids/fine", data=fine)
            f.create_dataset("grids/coarse", data=coarse)
            for k, split in enumerate(SPLITS):
                sl = slice(bounds[k], bounds[k + 1])
                _write_split(f.create_group(split), scene, initial[sl], masks[sl], times, fine, coarse)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


# ---------------------------------------------------------------------------------------------------
# reuse
# ---------------------------------------------------------------------------------------------------
def _file_problem(path: Path, expected: dict[str, Any]) -> Optional[tuple[str, str]]:
    """None if the file at `path` is complete and matches `expected`; else (kind, message)."""
    try:
        with _open(path) as f:
            found = _read_attributes(f, path)
            diffs = _differences({k: found.get(k) for k in expected}, expected)
            if diffs:
                return "mismatch", "; ".join(diffs)
            _check_structure(f, path, SPLITS)
    except DatasetError as exc:
        return "corrupt", str(exc)
    return None


def ensure_dataset(scene: Any, cfg: DatasetConfig, path: str | os.PathLike,
                   on_mismatch: str = "regenerate") -> Path:
    """Return `path`, generating it if absent, corrupt or generated with other settings.

    on_mismatch: "regenerate" (log a warning naming the differences, regenerate) or "error" (raise
    DatasetError naming the differing keys with both values). A mismatching file is never reused.
    """
    if on_mismatch not in ("regenerate", "error"):
        raise DatasetError(f"data.on_mismatch must be 'regenerate' or 'error', got {on_mismatch!r}")
    path = Path(path)
    if not path.exists():
        return generate_dataset(scene, cfg, path)
    problem = _file_problem(path, generation_attributes(scene, cfg))
    if problem is None:
        log.info("reusing dataset %s", path)
        return path
    kind, detail = problem
    if on_mismatch == "error":
        raise DatasetError(_mismatch_message(path, [detail]) if kind == "mismatch" else detail)
    log.warning("regenerating dataset %s: %s", path,
                f"settings differ ({detail})" if kind == "mismatch" else detail)
    return generate_dataset(scene, cfg, path)


# ---------------------------------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------------------------------
def observed_index(masks: np.ndarray) -> np.ndarray:
    """Each trajectory's observed coarse points as sorted indices (n, Nobs), from its masks (n, Nc) bool."""
    return np.stack([np.flatnonzero(m) for m in masks])


@dataclass
class TrajectorySplit:
    """One split of a dataset, in memory. n trajectories, T samples, Nf fine / Nc coarse points.

    times (T,) [s]; fine_points (Nf, dim_B), coarse_points (Nc, dim_B) float32; states (n, T, S);
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

    def __len__(self) -> int:
        return self.states.shape[0]

    @property
    def train_times(self) -> int:
        """Number of leading samples used for training (from the generation attributes)."""
        return int(self.attrs["generation"]["train_times"])

    def observed(self, max_time: int | None = None, velocities: bool = False) -> tuple[np.ndarray, ...]:
        """Each trajectory's masked coarse observations over its first `max_time` samples (all if None).

        Returns points (n, Nobs, dim_B) float32 and values (n, T', Nobs, A) float32, and with
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
    """Load and validate one split; with `scene`/`cfg`, also check the file was generated from them."""
    path = Path(path)
    if split not in SPLITS:
        raise DatasetError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    if not path.is_file():
        raise DatasetError(f"{path}: dataset file not found; run `python -m lnf.train` (it generates the dataset) "
                           f"or call lnf.dataset.ensure_dataset(scene, cfg, path)")
    with _open(path) as f:
        attrs = _read_attributes(f, path)
        _check_version(path, attrs)
        if scene is not None or cfg is not None:
            exp = _expected(scene, cfg)
            diffs = _differences({k: attrs.get(k) for k in exp}, exp)
            if diffs:
                raise DatasetError(_mismatch_message(path, diffs))
        _check_structure(f, path, (split,))
        data = {name: _read_finite(f, path, key) for name, key in (
            ("times", "times"), ("fine_points", "grids/fine"), ("coarse_points", "grids/coarse"),
            ("states", f"{split}/states"), ("energy", f"{split}/energy"), ("fields", f"{split}/fields"),
            ("velocities", f"{split}/velocities"), ("coarse_fields", f"{split}/coarse_fields"),
            ("coarse_velocities", f"{split}/coarse_velocities"))}
        masks = f[f"{split}/masks"][...]
    return TrajectorySplit(masks=masks, attrs=attrs, **data)
