"""Your own trajectories as an lnf dataset: arrays from any simulator, on any points.

A researcher's data usually come from their own simulator (another language, a mesh): fields sampled at points
(mesh nodes, scattered sensors) at uniformly spaced times. :class:`Trajectories` holds one or more of them as
arrays; :func:`write_dataset` writes train/val/test trajectories as an HDF5 file that ``python -m lnf.train
data.path=<file>`` trains on with a scene that gives only its Lagrangian (no ``simulate()``, no ``fields()``)::

    from lnf.trajectories import Trajectories, write_dataset
    train = Trajectories(points=X, times=t, fields=q)          # X (N, dim_B), t (T,), q (n, T, N, A)
    write_dataset("data/mine.h5", train, val, test, scene=MyScene())

The file's own settings are trusted: training reads its counts, times, training horizon and observation
masks from it, whatever ``data.*`` says. Evaluation without a simulator is limited to the stored times and
points. Meshes with their point data are read by :func:`lnf.mesh_io.read_mesh_series`.

The file has the layout of a generated dataset (see :mod:`lnf.dataset`) with ``lnf_generation["source"] =
"arrays"``: the evaluation points are the given points (``/grids/fine``), the observation points the same ones
(``/grids/coarse`` is a link, not a copy), each trajectory observes a fixed random subset of
``observed_fraction`` of them, and the optional arrays are stored where given: quadrature weights
(``/grids/weights``), states, energy parts (``/{split}/kinetic``, ``/{split}/potential``, and their sum
``energy``) and per-trajectory loads (``/{split}/controls``).
"""
from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from lnf.dataset import (CHECKSUM_ALGORITHM, CHECKSUM_ATTR, FORMAT_VERSION, SOURCE_ARRAYS, DatasetError, atomic_h5,
                         check_points, scene_record, write_root_attributes)
from lnf.dataset.generate import _size, _write_array
from lnf.dataset.verify import _little_endian

log = logging.getLogger("lnf.trajectories")

TIME_TOLERANCE = 1e-6  # relative spread of the time steps that still counts as uniform


def _array(name: str, value: Any, ndim: Sequence[int], dtype: Any = np.float64) -> np.ndarray:
    """`value` as a finite real array of one of the dimensions `ndim`, or a DatasetError naming `name`. A masked
    array (what netCDF readers return) with masked elements is refused: np.asarray would drop its mask and keep
    the fill values (e.g. 1e20) as data."""
    if np.ma.isMaskedArray(value):
        masked = np.ma.getmaskarray(value)
        if masked.any():
            first = np.argwhere(masked)[0].tolist()
            raise DatasetError(f"{name}: got a masked array with {int(masked.sum())} masked (missing) values of "
                               f"{masked.size} (the first at index {first}); lnf would otherwise store their fill "
                               f"values (e.g. {np.ma.default_fill_value(value)!r}) as data. Fill or drop the missing "
                               f"values yourself (e.g. interpolate them, or leave out those points or trajectories) "
                               f"and pass a plain array")
        value = np.ma.getdata(value)
    kind = getattr(getattr(value, "dtype", None), "is_complex", None)  # a torch tensor's dtype says so itself
    if kind is True or (kind is None and np.iscomplexobj(value)):
        raise DatasetError(f"{name}: got a complex array (dtype {value.dtype if hasattr(value, 'dtype') else 'complex'}"
                           f"); lnf expects real floating-point values (converting would drop the imaginary part): "
                           f"pass its real part, its magnitude, or the real and imaginary parts as two components")
    try:
        arr = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{name}: expected a numeric array, got {type(value).__name__} ({exc})") from exc
    if arr.ndim not in ndim:
        raise DatasetError(f"{name}: expected an array of {' or '.join(map(str, ndim))} dimensions, got shape "
                           f"{arr.shape}")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0].tolist()
        raise DatasetError(f"{name}: {int((~np.isfinite(arr)).sum())} values are NaN or inf (the first at index "
                           f"{bad}); lnf trains only on finite data")
    return arr


FLOAT32_TOLERANCE = 1e-4  # RMS change by float32 rounding, relative to the values' own spread, that is refused


def _check_float32(name: str, given: Any, stored: np.ndarray) -> None:
    """`stored` (n, T, N, A) float32, as the file keeps it, against `given`, the values passed (any precision): per
    component, the RMS rounding change relative to the values' own standard deviation (over all trajectories,
    times and points) must stay ≤ FLOAT32_TOLERANCE, else DatasetError naming `name`, the loss and the fix (a
    large offset leaves float32 too few digits for the variation). Read one trajectory at a time; values already
    in float32 (or coarser) lose nothing and are not read."""
    given = np.ma.getdata(given) if np.ma.isMaskedArray(given) else given
    src = np.asarray(given)
    if src.dtype.kind == "f" and src.dtype.itemsize <= 4:
        return
    n, A = stored.shape[0], stored.shape[-1]

    def rows(i: int) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(src[i], dtype=np.float64).reshape(-1, A), stored[i].reshape(-1, A).astype(np.float64)

    count, total = 0, np.zeros(A)
    for i in range(n):
        x, _ = rows(i)
        count, total = count + x.shape[0], total + x.sum(axis=0)
    mean = total / max(count, 1)
    var, err2, err_max = np.zeros(A), np.zeros(A), np.zeros(A)
    for i in range(n):  # a second pass: the spread about the mean, exact even under a large offset
        x, y = rows(i)
        var += ((x - mean) ** 2).sum(axis=0)
        err2 += ((x - y) ** 2).sum(axis=0)
        err_max = np.maximum(err_max, np.abs(x - y).max(axis=0, initial=0.0))
    std, rms = np.sqrt(var / max(count, 1)), np.sqrt(err2 / max(count, 1))
    varies = std > 1e-12 * np.abs(mean)  # below: a constant component (its spread is float64 round-off), no signal
    with np.errstate(divide="ignore", invalid="ignore"):
        loss = np.where(varies & (std > 0), rms / np.where(std > 0, std, 1.0), 0.0)
    if not (loss > FLOAT32_TOLERANCE).any():
        return
    a = int(np.argmax(loss))
    where = f"component {a} of {name}" if A > 1 else name
    raise DatasetError(f"{name}: lnf stores fields and velocities in float32 (its dataset files and its model), and "
                       f"rounding {where} to float32 changes them by up to {err_max[a]:.3g} (RMS {rms[a]:.3g}), "
                       f"{loss[a]:.2g} of their own spread (standard deviation {std[a]:.3g} about a mean of "
                       f"{mean[a]:.7g}; at most {FLOAT32_TOLERANCE:g} is accepted): their offset is "
                       f"{abs(mean[a]) / std[a]:.3g} times their variation, more than float32's ~7 significant digits "
                       f"resolve, so the variation would be silently lost. Subtract an offset (e.g. the mean, or a "
                       f"reference configuration: values - values.mean(axis=(0, 1, 2))) and/or rescale, the same for "
                       f"every split, and pass them again")


@dataclass
class Trajectories:
    """n trajectories of a field with A components on N points of a dim_B-dimensional body, at T times.

    Attributes:
        points: (N, dim_B) material points [the body's length unit]: mesh nodes, sensors, a grid; any order.
        times: (T,) [s], uniformly spaced from 0 (t_k = k·dt).
        fields: (n, T, N, A) the configuration field q at the points ((n, T, N) for a scalar field).
        velocities: (n, T, N, A) q̇, or None: then second-order central differences in time of `fields`
            (one-sided at the ends; recorded in the file).
        weights: (N,) quadrature weights of the points (e.g. lumped nodal volumes of a mesh), or None. With them
            ``quadrature=stored`` integrates the reduced dynamics on these points and the field errors are
            weighted by them; without them the errors weigh all points equally.
        states: (n, T, S) full-order states, or None (evaluation never needs them for the stored times).
        kinetic, potential: (n, T) the reference energy parts, or None (then the energy errors are not
            computed, unless the scene gives ``true_energy_parts`` of `states`).
        controls: (n, c) per-trajectory load parameters that the scene's generalized force takes, or None.
    """

    points: np.ndarray
    times: np.ndarray
    fields: np.ndarray
    velocities: Optional[np.ndarray] = None
    weights: Optional[np.ndarray] = None
    states: Optional[np.ndarray] = None
    kinetic: Optional[np.ndarray] = None
    potential: Optional[np.ndarray] = None
    controls: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        self.points = _array("points", self.points, (1, 2))
        if self.points.ndim == 1:
            self.points = self.points[:, None]
        N, dim_b = self.points.shape
        if N < 1 or not 1 <= dim_b <= 3:
            raise DatasetError(f"points: expected shape (N ≥ 1, dim_B ∈ 1..3), got {self.points.shape}")
        self.times = _array("times", self.times, (1,))
        T = len(self.times)
        if T < 2:
            raise DatasetError(f"times: need at least 2 samples, got {T}")
        steps = np.diff(self.times)
        dt = float(steps.mean())
        if abs(self.times[0]) > TIME_TOLERANCE * dt:
            raise DatasetError(f"times: must start at 0 (t_k = k·dt), got t_0 = {self.times[0]!r}; pass "
                               f"times - times[0]")
        if dt <= 0 or np.abs(steps - dt).max() > TIME_TOLERANCE * dt:
            raise DatasetError(f"times: must be uniformly spaced and increasing (the reduced model integrates with "
                               f"one step dt), got steps from {steps.min()!r} to {steps.max()!r} s; resample them")
        given = self.fields
        self.fields = _array("fields", self.fields, (3, 4), np.float32)
        if self.fields.ndim == 3:
            self.fields = self.fields[..., None]
        _check_float32("fields", given, self.fields)
        n = self.fields.shape[0]
        if self.fields.shape[1:3] != (T, N) or n < 1 or self.fields.shape[3] < 1:
            raise DatasetError(f"fields: expected shape (n, T, N, A) = (n, {T}, {N}, A) for {T} times and {N} "
                               f"points, got {self.fields.shape}")
        if self.velocities is None:
            self.velocities = np.gradient(self.fields.astype(np.float64), dt, axis=1, edge_order=2)
            self._velocities_given = False
        else:
            self._velocities_given = True
        given = self.velocities
        self.velocities = _array("velocities", self.velocities, (3, 4), np.float32)
        if self.velocities.ndim == 3:
            self.velocities = self.velocities[..., None]
        if self.velocities.shape != self.fields.shape:
            raise DatasetError(f"velocities: expected the shape of fields {self.fields.shape}, got "
                               f"{self.velocities.shape}")
        _check_float32("velocities" if self._velocities_given else "velocities (central differences of fields)",
                       given, self.velocities)
        if self.weights is not None:
            self.weights = _array("weights", self.weights, (1,))
            if self.weights.shape != (N,) or (self.weights <= 0).any():
                raise DatasetError(f"weights: expected ({N},) positive quadrature weights, one per point, got shape "
                                   f"{self.weights.shape} with minimum {self.weights.min() if self.weights.size else '-'}")
        if self.states is not None:
            self.states = _array("states", self.states, (3,))
            if self.states.shape[:2] != (n, T):
                raise DatasetError(f"states: expected shape (n, T, S) = ({n}, {T}, S), got {self.states.shape}")
        if (self.kinetic is None) != (self.potential is None):
            raise DatasetError("kinetic and potential: give both energy parts or neither")
        for key in ("kinetic", "potential"):
            if getattr(self, key) is not None:
                setattr(self, key, _array(key, getattr(self, key), (2,)))
                if getattr(self, key).shape != (n, T):
                    raise DatasetError(f"{key}: expected shape (n, T) = ({n}, {T}), got {getattr(self, key).shape}")
        if self.controls is not None:
            self.controls = _array("controls", self.controls, (2,))
            if self.controls.shape[0] != n:
                raise DatasetError(f"controls: expected shape (n, c) with n = {n}, got {self.controls.shape}")

    def __len__(self) -> int:
        return self.fields.shape[0]

    @property
    def dt(self) -> float:
        """The time step [s]."""
        return float(np.diff(self.times).mean())

    @property
    def velocities_given(self) -> bool:
        """False when the velocities were taken from central differences of the fields."""
        return getattr(self, "_velocities_given", True)

    def select(self, index: Any) -> "Trajectories":
        """The trajectories `index` (an int, slice or index array) of these, with the same points and times."""
        idx = np.arange(len(self))[index]
        idx = np.atleast_1d(idx)
        part = replace(self, fields=self.fields[idx], velocities=self.velocities[idx],
                       states=None if self.states is None else self.states[idx],
                       kinetic=None if self.kinetic is None else self.kinetic[idx],
                       potential=None if self.potential is None else self.potential[idx],
                       controls=None if self.controls is None else self.controls[idx])
        part._velocities_given = self.velocities_given
        return part

    @staticmethod
    def stack(items: Sequence["Trajectories"]) -> "Trajectories":
        """One :class:`Trajectories` of all trajectories of `items` (the same points, weights and times, e.g. one
        :func:`lnf.mesh_io.read_mesh_series` per simulation run)."""
        if not items:
            raise DatasetError("Trajectories.stack: no trajectories given")
        first = items[0]
        for i, item in enumerate(items[1:], 1):
            _same(f"trajectories {i}", item, first)
        for key in ("states", "kinetic", "controls"):
            if len({getattr(t, key) is None for t in items}) > 1:
                raise DatasetError(f"Trajectories.stack: {key} given for some trajectories and not for others")

        def cat(key: str) -> Optional[np.ndarray]:
            return None if getattr(first, key) is None else np.concatenate([getattr(t, key) for t in items])

        out = Trajectories(points=first.points, times=first.times, fields=cat("fields"), velocities=cat("velocities"),
                           weights=first.weights, states=cat("states"), kinetic=cat("kinetic"),
                           potential=cat("potential"), controls=cat("controls"))
        out._velocities_given = all(t.velocities_given for t in items)
        return out


def _same(name: str, part: Trajectories, ref: Trajectories) -> None:
    """`part` has the points, times, field components, weights and optional arrays of `ref`."""
    if part.points.shape != ref.points.shape:
        raise DatasetError(f"{name}: its points have shape {part.points.shape}, the training trajectories' "
                           f"{ref.points.shape} (every split must be sampled on the same points)")
    if not np.allclose(part.points, ref.points, rtol=0, atol=1e-9):
        raise DatasetError(f"{name}: its points differ from those of the training trajectories by up to "
                           f"{np.abs(part.points - ref.points).max():.3g} (every split must be sampled on the same "
                           f"points, in the same order)")
    if part.times.shape != ref.times.shape or not np.allclose(part.times, ref.times, rtol=1e-9, atol=0):
        raise DatasetError(f"{name}: its times differ from those of the training trajectories ({len(part.times)} "
                           f"samples, dt = {part.dt:g} s, against {len(ref.times)}, dt = {ref.dt:g} s)")
    if part.fields.shape[3] != ref.fields.shape[3]:
        raise DatasetError(f"{name}: its fields have {part.fields.shape[3]} components, the training trajectories' "
                           f"{ref.fields.shape[3]}")
    if (part.weights is None) != (ref.weights is None) or (
            part.weights is not None and not np.allclose(part.weights, ref.weights)):
        raise DatasetError(f"{name}: its quadrature weights differ from those of the training trajectories")
    for key, width in (("states", lambda a: a.shape[2]), ("controls", lambda a: a.shape[1])):
        a, b = getattr(part, key), getattr(ref, key)
        if (a is None) != (b is None) or (a is not None and width(a) != width(b)):
            raise DatasetError(f"{name}: {key} must be given for every split with the same width, or for none")
    if (part.kinetic is None) != (ref.kinetic is None):
        raise DatasetError(f"{name}: energies (kinetic, potential) must be given for every split, or for none")


def _check_scene(scene: Any, data: Trajectories) -> None:
    """The scene's body dimension and field components match the arrays; the points lie in its box."""
    dim_b, A = data.points.shape[1], data.fields.shape[3]
    if scene.body_dim != dim_b:
        raise DatasetError(f"points have {dim_b} coordinates, but scene {scene.name!r} has a {scene.body_dim}-D body "
                           f"(scene.bounds = {scene.bounds})")
    if int(scene.field_dim) != A:
        raise DatasetError(f"fields have {A} components, but scene {scene.name!r} has field_dim = {scene.field_dim}")
    box = np.asarray(scene.bounds, dtype=np.float64)
    slack = 1e-6 * (box[:, 1] - box[:, 0])
    outside = ((data.points < box[:, 0] - slack) | (data.points > box[:, 1] + slack)).any(axis=1)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        raise DatasetError(f"points: {int(outside.sum())} of {len(outside)} lie outside scene.bounds = "
                           f"{scene.bounds} of scene {scene.name!r}, e.g. point {i} at {data.points[i].tolist()}; "
                           f"give the scene bounds that hold the whole body")


def _trajectory_keys(part: Trajectories) -> list[bytes]:
    """One digest per trajectory of what identifies it: its fields, velocities, states and controls (bit for bit)."""
    keys = []
    for i in range(len(part)):
        h = hashlib.blake2b(digest_size=20)
        for arr in (part.fields, part.velocities, part.states, part.controls):
            if arr is not None:
                h.update(_little_endian(np.asarray(arr[i])))
        keys.append(h.digest())
    return keys


def _check_disjoint(path: Path, splits: dict[str, Trajectories]) -> None:
    """No trajectory (identical fields, velocities, states and controls) in train and also in val or test: that
    leaks the training data into validation (model selection) or the test errors → DatasetError naming both splits
    and a pair. One shared by val and test only → a warning (the test errors stay honest, the selection does not)."""
    keys = {name: _trajectory_keys(part) for name, part in splits.items()}
    for a, b in (("train", "test"), ("train", "val"), ("val", "test")):
        first = {k: i for i, k in reversed(list(enumerate(keys[a])))}
        shared = [(first[k], j) for j, k in enumerate(keys[b]) if k in first]
        if not shared:
            continue
        i, j = shared[0]
        whole = (f"the {b} split is identical to the {a} split" if len(shared) == len(keys[b]) == len(keys[a]) and
                 all(x == y for x, y in shared) else
                 f"{len(shared)} of the {len(keys[b])} {b} trajectories {'is' if len(shared) == 1 else 'are'} "
                 f"also in the {a} split")
        detail = (f"{path}: {whole} (e.g. {b} trajectory {j} is {a} trajectory {i}: the same fields, velocities, "
                  f"states and controls)")
        if a == "train":
            raise DatasetError(f"{detail}; a trajectory in train and also in {b} leaks the training data into the "
                               f"{b} errors: give {b} other trajectories than train (e.g. runs.select(slice(0, "
                               f"n_train)) and runs.select(slice(n_train, None)) of distinct runs)")
        log.warning("%s; the validation loss that selects the model then also measures the test trajectories; give "
                    "val trajectories of its own for honest test errors", detail)


def _masks(n: int, n_points: int, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """(n, N) bool: each trajectory's fixed random subset of round(fraction·N) ≥ 1 observed points."""
    n_obs = int(round(fraction * n_points))
    if n_obs < 1:
        raise DatasetError(f"observed_fraction = {fraction} observes 0 of the {n_points} points; raise it")
    masks = np.zeros((n, n_points), dtype=bool)
    for i in range(n):
        masks[i, rng.permutation(n_points)[:n_obs]] = True
    return masks


def _write_fields(group: Any, key: str, values: np.ndarray) -> None:
    """(n, T, N, A) float32 in one chunk per trajectory-time slab, with its checksum."""
    n, T = values.shape[:2]
    ds = group.create_dataset(key, shape=values.shape, dtype=np.float32, chunks=(1, 1) + values.shape[2:])
    h = hashlib.blake2b()
    for i in range(n):
        ds[i] = values[i]
        h.update(_little_endian(np.asarray(values[i], dtype=np.float32)))
    ds.attrs[CHECKSUM_ATTR] = f"{CHECKSUM_ALGORITHM}:{h.hexdigest()}"


def write_dataset(path: str | os.PathLike, train: Trajectories, val: Trajectories, test: Trajectories, *,
                  scene: Any = None, train_times: Optional[int] = None, observed_fraction: float = 0.25,
                  seed: int = 0, overwrite: bool = False) -> Path:
    """Write trajectories from any simulator as an lnf dataset at `path` (atomically); returns the path.

    Args:
        train, val, test: the splits (disjoint trajectories on the same points and times). Training learns from
            `train` (and validates on `val`) over the first `train_times` samples; the test split is rolled out
            over all of them, so errors after `train_times` measure extrapolation in time.
        scene: the scene to record (its spec); training then refuses another scene. None records no scene: any
            scene whose body dimension and field components match may train on the file. With a scene, its
            ``true_energy_parts`` gives the energies where `states` but no energies are given.
        train_times: samples per trajectory used for training (default: the first half, T // 2).
        observed_fraction: each trajectory observes a fixed random subset of this fraction of the points (a
            training snapshot is that subset; seeded by `seed`).
        overwrite: replace an existing file at `path` (default False: an existing file is an error, never lost).

    Refused as well (the data would be silently wrong): complex arrays; distinct points that float32, the model's
    precision, would merge (shift or scale the coordinates; the points are stored in float64, as given); a point
    given twice with different values; a trajectory (the same fields, velocities, states and controls) in train and
    also in val or test, a leak (one shared by val and test only is a warning).

    Every failure is a DatasetError naming the argument, its shape or the file.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise DatasetError(f"{path}: a file exists there; pass overwrite=True to replace it, or another path")
    splits = {"train": train, "val": val, "test": test}
    for name, part in splits.items():
        if not isinstance(part, Trajectories):
            raise DatasetError(f"{name}: expected lnf.trajectories.Trajectories, got {type(part).__name__}")
        if name != "train":
            _same(name, part, train)
    T, N, A = train.fields.shape[1:]
    train_times = T // 2 if train_times is None else train_times
    if isinstance(train_times, bool) or int(train_times) != train_times or not 1 <= int(train_times) <= T:
        raise DatasetError(f"train_times must be an integer in [1, {T}] (samples used for training), got "
                           f"{train_times!r}")
    if not 0 < float(observed_fraction) <= 1:
        raise DatasetError(f"observed_fraction must be in (0, 1], got {observed_fraction!r}")
    check_points(f"{path}: points", train.points, {f"{name} {key}": getattr(part, key) for name, part in splits.items()
                                                   for key in ("fields", "velocities")})
    _check_disjoint(path, splits)
    energies = "given" if train.kinetic is not None else "none"
    if scene is not None:
        _check_scene(scene, train)
        if energies == "none" and train.states is not None and scene.provides("true_energy_parts"):
            for part in splits.values():
                part.kinetic, part.potential = (np.asarray(e, dtype=np.float64)
                                                for e in scene.true_energy_parts(part.states))
            energies = "scene"
    spec = scene_record(scene) if scene is not None else None
    generation = {"source": SOURCE_ARRAYS, "n_train": len(train), "n_val": len(val), "n_test": len(test),
                  "n_times": int(T), "dt": train.dt, "train_times": int(train_times), "n_points": int(N),
                  "observed_fraction": float(observed_fraction), "seed": int(seed),
                  "velocities": "given" if all(p.velocities_given for p in splits.values()) else "central differences",
                  "energies": energies, "weights": train.weights is not None}
    rng = np.random.default_rng(int(seed))
    n_total = sum(len(p) for p in splits.values())
    S = 0 if train.states is None else train.states.shape[2]
    needed = int(1.05 * (N * (train.points.shape[1] + 1) * 8 + T * 8 + n_total * (
        2 * T * N * A * 4 + N + T * (S + 3) * 8))) + (1 << 20)
    log.info("writing %d trajectories × %d samples on %d points to %s (≤ %s)", n_total, T, N, path, _size(needed))
    with atomic_h5(path, needed) as f:
        write_root_attributes(f, spec, generation, str(scene.name) if scene is not None else "arrays")
        _write_array(f, "times", train.dt * np.arange(T, dtype=np.float64))
        _write_array(f, "grids/fine", train.points.astype(np.float64))  # a mesh's nodes exactly, not rounded
        f["grids/coarse"] = f["grids/fine"]  # observations are taken at the same points: a link, not a copy
        if train.weights is not None:
            _write_array(f, "grids/weights", train.weights)
        for name, part in splits.items():
            group = f.create_group(name)
            states = part.states if part.states is not None else np.zeros((len(part), T, 0))
            _write_array(group, "states", states)
            _write_array(group, "masks", _masks(len(part), N, float(observed_fraction), rng))
            if part.kinetic is not None:
                _write_array(group, "kinetic", part.kinetic)
                _write_array(group, "potential", part.potential)
                _write_array(group, "energy", part.kinetic + part.potential)
            if part.controls is not None:
                _write_array(group, "controls", part.controls)
            _write_fields(group, "fields", part.fields)
            _write_fields(group, "velocities", part.velocities)
            group["coarse_fields"] = group["fields"]
            group["coarse_velocities"] = group["velocities"]
    return path


__all__ = ["Trajectories", "write_dataset", "FORMAT_VERSION"]
