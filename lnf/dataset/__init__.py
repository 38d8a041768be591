"""Ground-truth trajectory datasets in HDF5 (docs/method.md §7.1): generation, reuse checks, loading.

Modules: ``format`` (version, keys, attribute names, errors), ``config`` (:class:`DatasetConfig`), ``verify``
(structure, checksums, finiteness), ``generate`` (simulation and the atomic write), ``reuse``
(:func:`ensure_dataset`), ``load`` (:func:`load_split`). Every public name is importable from ``lnf.dataset``.

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
