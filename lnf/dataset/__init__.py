"""Ground-truth trajectory datasets in HDF5 (docs/method.md §7.1): generation, reuse checks, loading.

Modules: ``format`` (version, keys, attribute names, errors), ``config`` (:class:`DatasetConfig`), ``verify``
(structure, checksums, finiteness), ``generate`` (simulation and the atomic write), ``reuse``
(:func:`ensure_dataset`), ``load`` (:func:`load_split`): every public name of these is importable from ``lnf.dataset``. ``snapshots``
(:class:`SnapshotData`, a file as a model learns from it; it imports ``lnf.model``) is imported as ``lnf.dataset.snapshots``.

The file layout (``FORMAT_VERSION`` 2: splits, grids, masks, files from a user's arrays), its checksums and
manifest, the atomic writes, the disk-space check and the reuse rules are described in docs/data_format.md. Every
user-facing failure raises :class:`DatasetError` naming the file and the key.
"""
from __future__ import annotations

from lnf.dataset.format import (
    ARRAYS_HINT, ATTRIBUTES_CHECKSUM_ATTR, BLOCK_BYTES, CHECKSUM_ALGORITHM, CHECKSUM_ATTR, COARSE_GRIDS,
    DAMAGED_SUFFIX, DatasetError, ERROR_HINT, FIELD_KEYS, FIX_HINT, FORMAT_VERSION, LOAD_HINT, MANIFEST_ATTR,
    OPTIONAL_SPLIT_KEYS, ROOT_ATTRIBUTES, SOURCE_ARRAYS, SPLITS, SPLIT_KEYS, log)
from lnf.dataset.config import DatasetConfig, generation_attributes, scene_record
from lnf.dataset.verify import check_points, content_checksum, dataset_keys, float32_collisions
from lnf.dataset.generate import (
    GROUND_TRUTH_FOLDER, SIMULATION_CHUNK, WORKERS_ENV, _simulate, atomic_h5, generate_dataset,
    simulated_ground_truth, simulation_chunks, simulation_workers, write_root_attributes)
from lnf.dataset.reuse import default_path, ensure_dataset, evaluation_data, not_lnf_dataset, warn_if_changed
from lnf.dataset.load import (
    TrajectorySplit, check_scene_fits, dataset_source, load_split, observed_index, stored_generation, verify_dataset)

__all__ = [
    "ARRAYS_HINT", "ATTRIBUTES_CHECKSUM_ATTR", "BLOCK_BYTES", "CHECKSUM_ALGORITHM", "CHECKSUM_ATTR", "COARSE_GRIDS",
    "DAMAGED_SUFFIX", "DatasetConfig", "DatasetError", "ERROR_HINT", "FIELD_KEYS", "FIX_HINT", "FORMAT_VERSION",
    "GROUND_TRUTH_FOLDER", "LOAD_HINT", "MANIFEST_ATTR", "OPTIONAL_SPLIT_KEYS", "ROOT_ATTRIBUTES",
    "SIMULATION_CHUNK", "SOURCE_ARRAYS", "SPLITS", "SPLIT_KEYS", "TrajectorySplit", "WORKERS_ENV", "atomic_h5",
    "check_points", "check_scene_fits", "content_checksum", "dataset_keys", "dataset_source", "default_path",
    "ensure_dataset", "evaluation_data",
    "float32_collisions", "generate_dataset", "generation_attributes", "load_split", "log", "not_lnf_dataset",
    "observed_index", "scene_record", "simulated_ground_truth", "simulation_chunks", "simulation_workers",
    "stored_generation", "verify_dataset", "warn_if_changed", "write_root_attributes"]
