"""Loading a split of a verified dataset: TrajectorySplit and load_split."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Optional

import h5py
import numpy as np

from lnf.dataset.config import DatasetConfig, _differences, _expected, _mismatch_message, scene_record
from lnf.dataset.format import ARRAYS_HINT, DatasetError, LOAD_HINT, SOURCE_ARRAYS, SPLITS, _Damaged, log
from lnf.dataset.verify import (
    _check_generation, _check_manifest, _check_structure, _check_version, _dataset, _is_arrays_file, _open,
    _points_hint, _read_attributes, _read_verified, _verify_all, _verify_attributes, check_points)


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

    def loads(self, scene: Any = None) -> Optional[np.ndarray]:
        """The per-trajectory load parameters (n, c): stored ones, else ``scene.controls`` of the initial states (as
        lnf's evaluation reads them); None for a scene without loads."""
        if self.controls is not None:
            return self.controls
        if scene is not None and self.states.shape[-1] > 0:
            return scene.controls(np.asarray(self.states[:, 0]))
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
