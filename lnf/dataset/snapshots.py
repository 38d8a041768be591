"""A dataset file as a model learns from it: the masked coarse snapshots (:class:`SnapshotDataset`) and the file's
handle (:class:`SnapshotData`: generation or verification, splits, snapshots), in plain torch. lnf.train's Lightning
data module (lnf/training/datamodule.py) adds only the loaders."""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any, Optional

import h5py
import numpy as np
import torch
from torch.utils.data import Dataset

from lnf.closure import central_difference4
from lnf.dataset.config import DatasetConfig
from lnf.dataset.format import SOURCE_ARRAYS, DatasetError
from lnf.dataset.load import TrajectorySplit, dataset_source, load_split, observed_index, stored_generation
from lnf.dataset.reuse import default_path, ensure_dataset
from lnf.dataset.verify import content_checksum
from lnf.model import build
from lnf.scenes.base import Scene
from lnf.utils import require

log = logging.getLogger("lnf.data")


def _read_leading(dataset: h5py.Dataset, n_times: int) -> np.ndarray:
    """dataset[:, :n_times] read straight into one array (slicing would hold a second copy at its peak)."""
    out = np.empty((dataset.shape[0], n_times, *dataset.shape[2:]), dtype=dataset.dtype)
    dataset.read_direct(out, np.s_[:, :n_times])
    return out


class SnapshotDataset(Dataset):
    """Snapshots (trajectory i, time k < n_times) of each trajectory's own masked coarse observations.

    Reads the HDF5 file lazily: each process (DataLoader worker, DDP rank) opens its own read-only handle
    on first use and reads one snapshot per item, so memory does not grow with the dataset. With
    ``in_memory`` the split's coarse values and velocities over the first `n_times` samples are read once.

    Item: a dict of float32 tensors, ``points`` (Nobs, dim_B), ``values`` (Nobs, A), ``velocities`` (Nobs, A), with
    `scene` given also ``potential``, the snapshot's full-order potential energy V (0-d, from the stored states
    through ``scene.true_energy_parts``: the target of the optional energy loss), and with `gradient_scene` given
    ``gradients``, the full-order ∇_X q at the observed points (Nobs, A, dim_B), from ``scene.field_gradients``
    (the target of the optional gradient loss); the loader stacks items into a
    :class:`lnf.training.batch.SnapshotBatch`. With ``noise`` > 0, item
    (i, k) gets Gaussian noise of std noise·RMS (RMS of the split's observed values, resp. velocities) drawn
    from a generator seeded by (seed, i, k): the same noise in both modes, in any worker, after a restart.
    """

    KEYS = ("coarse_fields", "coarse_velocities")

    def __init__(self, path: str | Path, split: str, n_times: int, noise: float = 0.0, seed: int = 0,
                 in_memory: bool = False, scene: Optional[Scene] = None,
                 gradient_scene: Optional[Scene] = None, accelerations: bool = False) -> None:
        self.path, self.split, self.n_times = Path(path), split, int(n_times)
        self.noise, self.seed, self.accelerations = float(noise), int(seed), bool(accelerations)
        with h5py.File(self.path, "r") as f:
            self.dt = float(f["times"][1] - f["times"][0]) if f["times"].shape[0] > 1 else float("nan")
            masks = f[f"{split}/masks"][...]
            self.index = observed_index(masks)  # (n, Nobs)
            self.points = torch.as_tensor(f["grids/coarse"][...][self.index], dtype=torch.float32)
            self._arrays = {key: _read_leading(f[f"{split}/{key}"], self.n_times) for key in self.KEYS} \
                if in_memory else None
            stateless = f[f"{split}/states"].shape[-1] == 0  # trajectories written from arrays without states
            if scene is None:
                self.potential = None
            elif f"{split}/potential" in f:  # stored with the trajectories
                self.potential = torch.as_tensor(f[f"{split}/potential"][:, :self.n_times], dtype=torch.float32)
            elif stateless:
                raise DatasetError(f"{self.path}: model.energy_weight > 0 needs each snapshot's potential energy, and "
                                   f"the file has neither energies nor states; write the trajectories with kinetic= "
                                   f"and potential= (lnf.trajectories.Trajectories), or set model.energy_weight=0")
            else:
                self.potential = torch.as_tensor(np.stack([  # (n, n_times), one trajectory at a time
                    scene.true_energy_parts(f[f"{split}/states"][i, :self.n_times])[1]
                    for i in range(self.index.shape[0])]), dtype=torch.float32)
            if gradient_scene is not None and stateless:
                raise DatasetError(f"{self.path}: model.gradient_weight > 0 needs ∇_X q from the scene's "
                                   f"field_gradients(states, points), and the file holds no states; set "
                                   f"model.gradient_weight=0")
            coarse = f["grids/coarse"][...]
            self.gradients = None if gradient_scene is None else torch.as_tensor(np.stack([  # (n, n_times, Nobs, A, dim_B)
                gradient_scene.field_gradients(f[f"{split}/states"][i, :self.n_times], coarse[self.index[i]])
                for i in range(self.index.shape[0])]), dtype=torch.float32)
        self._file: Optional[h5py.File] = None
        self._pid: Optional[int] = None
        self.noise_std = (self.noise * self._observed_rms(self.KEYS[0]), self.noise * self._observed_rms(self.KEYS[1])) \
            if self.noise > 0 else None

    def __len__(self) -> int:
        return self.index.shape[0] * self.n_times

    def __getstate__(self) -> dict[str, Any]:  # h5py handles do not pickle: each worker opens its own
        return {**self.__dict__, "_file": None, "_pid": None}

    def _source(self, key: str) -> Any:
        if self._arrays is not None:
            return self._arrays[key]
        if self._file is None or self._pid != os.getpid():
            self._file, self._pid = h5py.File(self.path, "r"), os.getpid()
        return self._file[f"{self.split}/{key}"]

    def _read(self, key: str, i: int, times: slice | int) -> np.ndarray:
        """Observed values of trajectory i at `times`: (Nobs, A) or (T', Nobs, A) float32, checked finite."""
        data = np.asarray(self._source(key)[i, times])[..., self.index[i], :]
        if not np.isfinite(data).all():
            raise DatasetError(f"{self.path}: dataset /{self.split}/{key} has non-finite values in trajectory {i} "
                               f"(times {times}): the file changed after it was verified at the start of the run; "
                               f"rerun the command (it regenerates a damaged file)")
        return data

    def _observed_rms(self, key: str) -> float:
        """RMS of the split's observed values of `key` over the first n_times samples (one trajectory at a time)."""
        total = count = 0.0
        for i in range(self.index.shape[0]):
            block = self._read(key, i, slice(0, self.n_times)).astype(np.float64)
            total, count = total + float(np.sum(block ** 2)), count + block.size
        return float(np.sqrt(total / max(count, 1)))

    def _noisy(self, i: int, k: int, values: np.ndarray, velocities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.noise_std is None:
            return values, velocities
        value_noise, velocity_noise = self._noise(i, k, values.shape)
        return values + value_noise, velocities + velocity_noise

    def _noise(self, i: int, k: int, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """The noise of item (i, k): of its values, then of its velocities (each `shape`, float32)."""
        rng = np.random.default_rng([self.seed, i, k])
        return tuple((std * rng.standard_normal(shape)).astype(np.float32) for std in self.noise_std)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        i, k = divmod(int(index), self.n_times)
        values, velocities = self._noisy(i, k, self._read(self.KEYS[0], i, k), self._read(self.KEYS[1], i, k))
        item = {"points": self.points[i], "values": torch.from_numpy(np.ascontiguousarray(values)),
                "velocities": torch.from_numpy(np.ascontiguousarray(velocities))}
        if self.potential is not None:
            item["potential"] = self.potential[i, k]
        if self.gradients is not None:
            item["gradients"] = self.gradients[i, k]
        if self.accelerations:
            item["accelerations"], item["acceleration_valid"] = self._acceleration(i, k)
        return item

    def _acceleration(self, i: int, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The observed acceleration field (Nobs, A) of snapshot (i, k): the fourth-order central difference
        (−u̇_{k+2} + 8u̇_{k+1} − 8u̇_{k−1} + u̇_{k−2}) / (12 dt) of the observed velocities (with the noise of their
        own items), and whether it exists (False within two samples of either end of the training window)."""
        if not 2 <= k < self.n_times - 2:
            shape = self.points[i].shape[:-1] + (self._source(self.KEYS[1]).shape[-1],)
            return torch.zeros(shape), torch.tensor(False)
        near = {j: self._read(self.KEYS[1], i, k + j) for j in (-2, -1, 1, 2)}
        if self.noise_std is not None:  # each neighbour's own noise; its values are not read
            near = {j: u + self._noise(i, k + j, u.shape)[1] for j, u in near.items()}
        acc = central_difference4(near[-2], near[-1], near[1], near[2], self.dt)
        return torch.from_numpy(np.ascontiguousarray(acc, dtype=np.float32)), torch.tensor(True)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All items stacked: points (n, Nobs, dim_B), values and velocities (n, n_times, Nobs, A)."""
        values, velocities = [], []
        for i in range(self.index.shape[0]):
            v, w = self._read(self.KEYS[0], i, slice(0, self.n_times)), self._read(self.KEYS[1], i, slice(0, self.n_times))
            pairs = [self._noisy(i, k, v[k], w[k]) for k in range(self.n_times)]
            values.append(np.stack([p[0] for p in pairs]))
            velocities.append(np.stack([p[1] for p in pairs]))
        return self.points.numpy(), np.stack(values), np.stack(velocities)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


class SnapshotData:
    """A dataset file and what a model may learn from it, without Lightning: generation or verification
    (:meth:`prepare_data`), the loaded splits (:meth:`split`) and the masked coarse snapshots (:meth:`snapshots`,
    :meth:`observations`). :class:`lnf.training.datamodule.SnapshotDataModule` adds the loaders that lnf.train uses;
    the evaluation, the closure fit and the studies need only this.

    Args: scene (object or spec), data_dir, path (None → :func:`default_path`), on_mismatch
    ('regenerate' | 'error'), batch_size (the global batch, shared among DDP processes), num_workers,
    noise (std of Gaussian noise added to the observed training values and velocities, relative to their
    RMS over the split; seeded by `seed`), in_memory (read the observations once instead of streaming them
    from the file), shuffle_seed (seed of the per-epoch batch order), and the :class:`DatasetConfig` fields.
    Set ``potential_targets`` (``lnf.train`` does when the model has an energy loss) before the first batch
    for items that also carry each snapshot's full-order potential energy, ``gradient_targets`` for items
    that also carry its ∇_X q at the observed points, and ``acceleration_targets`` for its observed acceleration
    field (the dynamics-residual loss's target)."""

    def __init__(self, scene: "Scene | dict", data_dir: str = "data", path: Optional[str] = None,
                 on_mismatch: str = "regenerate", batch_size: int = 32, num_workers: int = 0,
                 noise: float = 0.0, in_memory: bool = False, shuffle_seed: int = 0,
                 explicit_path: Optional[bool] = None, **generation: Any) -> None:
        super().__init__()
        self.scene = build(scene) if isinstance(scene, dict) else scene
        self.config = DatasetConfig.from_mapping(generation, ignore=("source", "generation", "checksum"))
        # an explicit path may be shared by runs with other settings: its file is never overwritten with them
        # (None: whether `path` is given; a checkpoint's describe() records it)
        self.explicit_path = bool(path) if explicit_path is None else bool(explicit_path)
        self.path = Path(path) if path else default_path(data_dir, self.scene, self.config)
        # trajectories written from arrays (lnf.trajectories.write_dataset): the file's own settings are trusted
        self.stored: Optional[dict[str, Any]] = None
        if path and dataset_source(self.path) == SOURCE_ARRAYS:
            self.stored = stored_generation(self.path)
            log.info("%s holds trajectories written from arrays: its own settings are used (%d/%d/%d train/val/test "
                     "trajectories, %d samples at dt = %g s, the first %d for training); the generation settings "
                     "data.n_*, data.dt, data.*_resolution, data.observed_fraction and data.seed are not used",
                     self.path, self.stored["n_train"], self.stored["n_val"], self.stored["n_test"],
                     self.stored["n_times"], self.stored["dt"], self.stored["train_times"])
        elif path and not self.path.exists() and not self.scene.capabilities()["simulator"]:
            raise DatasetError(f"data.path={path}: no file there, and scene {self.scene.name!r} has no simulator "
                               f"(simulate() and sample_initial_states()) to generate one; write your trajectories "
                               f"there with lnf.trajectories.write_dataset (see docs/own_system.md)")
        self._verified: Optional[tuple[int, int, int]] = None  # (inode, size, mtime) of the file last ensured
        # content checksum of the file when first ensured (lnf.dataset.content_checksum): a file replaced or rewritten
        # with other values later in the run (the test stage) is refused
        self.checksum: Optional[str] = None
        self.on_mismatch = on_mismatch
        self.batch_size = require("data.batch_size", batch_size, ("int", 1, None, ""))
        self.num_workers = require("data.num_workers", num_workers, ("int", 0, None, ""))
        self.noise = require("data.noise", noise, ("≥", 0, None, "relative noise std"))
        self.in_memory, self.shuffle_seed = bool(in_memory), int(shuffle_seed)
        self._splits: dict[str, TrajectorySplit] = {}
        self._snapshots: dict[str, SnapshotDataset] = {}
        self.potential_targets = False
        self.gradient_targets = False
        self.acceleration_targets = False

    @classmethod
    def from_settings(cls, settings: "dict[str, Any]", scene: "Scene | dict") -> "SnapshotData":
        """The handle of a run's ``data:`` settings (a plain mapping; its ``_target_``, lnf.train's data module, is
        left aside): what the studies read without Lightning."""
        return cls(scene=scene, **{k: v for k, v in settings.items() if k != "_target_"})

    @property
    def from_arrays(self) -> bool:
        """Whether the data are a user's trajectories written from arrays (no simulator behind them)."""
        return self.stored is not None

    @property
    def train_times(self) -> int:
        """Leading samples of each trajectory used for training."""
        return int(self.stored["train_times"]) if self.stored else self.config.train_times

    @property
    def dt(self) -> float:
        """Sample spacing [s]."""
        return float(self.stored["dt"]) if self.stored else self.config.dt

    @property
    def seed(self) -> int:
        """Seed of the masks (and of the training noise, offset)."""
        return int(self.stored["seed"]) if self.stored else self.config.seed

    def prepare_data(self) -> None:
        """Generate or verify (checksums: one read of the file) the dataset file; again (``setup``) only if the
        file changed since. At an explicit `path`, a file made with other settings raises DatasetError instead
        of being regenerated (two runs sharing the path would overwrite each other)."""
        def file_key() -> Optional[tuple[int, int, int]]:  # changes when the file is replaced or written
            st = self.path.stat() if self.path.is_file() else None
            return None if st is None else (st.st_ino, st.st_size, st.st_mtime_ns)

        if self._verified is not None and self._verified == file_key():
            return
        ensure_dataset(self.scene, self.config, self.path, on_mismatch=self.on_mismatch,
                       overwrite_other_settings=not self.explicit_path)
        self._verified = file_key()
        checksum = content_checksum(self.path)
        if self.checksum is not None and checksum != self.checksum:
            raise DatasetError(f"{self.path}: the file changed while this run was using it: its content checksum was "
                               f"{self.checksum} when the run first verified it, it is {checksum} now (the file was "
                               f"replaced or rewritten with other values); this run's results would mix the two files. "
                               f"Restore the file the run started with, or run the whole command again on the file as "
                               f"it is now")
        self.checksum = checksum

    def state_dict(self) -> dict[str, Any]:
        """Kept in checkpoints: the data file and its content checksum (:func:`lnf.dataset.content_checksum`)."""
        return {"path": str(self.path), "checksum": self.checksum} if self.checksum else {}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """A resumed checkpoint's record of its data file: a warning naming the file and both checksums when the
        file now holds other values than the checkpoint was trained on."""
        then = (state_dict or {}).get("checksum")
        if then and self.checksum and then != self.checksum:
            log.warning("%s changed since the resumed checkpoint was trained on it: its content checksum was %s, it is "
                        "%s now; training continues on the file as it is now, and the run's results mix the two "
                        "files (start afresh in a new output dir for results of this file alone)", self.path, then,
                        self.checksum)

    def split(self, name: str) -> TrajectorySplit:
        """The whole validated split ('train', 'val', 'test') in memory, loaded once (for evaluation)."""
        if name not in self._splits:
            self._splits[name] = load_split(self.path, name, scene=self.scene, cfg=self.config)
        return self._splits[name]

    def setup(self, stage: Optional[str] = None) -> None:
        self.prepare_data()

    def snapshots(self, split: str) -> SnapshotDataset:
        """What a model may learn from, one snapshot per item: each trajectory's masked coarse observations
        over the first `train_times` samples, with `noise` added to the training split (made once per split)."""
        if split in self._snapshots:
            return self._snapshots[split]
        noise = self.noise if split == "train" else 0.0
        self._snapshots[split] = SnapshotDataset(self.path, split, self.train_times, noise=noise,
                                                 seed=self.seed + 7919, in_memory=self.in_memory,
                                                 scene=self.scene if self.potential_targets else None,
                                                 gradient_scene=self.scene if self.gradient_targets else None,
                                                 accelerations=self.acceleration_targets)
        return self._snapshots[split]

    def observations(self, split: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All of :meth:`snapshots` at once: points (n, Nobs, dim_B), values and velocities (n, T', Nobs, A)."""
        return self.snapshots(split).arrays()

    def describe(self) -> dict[str, Any]:
        """Data settings to store in checkpoints (enough to regenerate the same file; for trajectories written from
        arrays, the file's path and its recorded settings, which lnf.evaluate checks the file still has)."""
        checksum = {"checksum": self.checksum} if self.checksum else {}  # once the file is ensured (prepare_data)
        if self.stored is not None:
            return {"path": str(self.path), "on_mismatch": self.on_mismatch, "explicit_path": True,
                    "source": SOURCE_ARRAYS, "generation": dict(self.stored), **checksum}
        return {"path": str(self.path), "on_mismatch": self.on_mismatch, "explicit_path": self.explicit_path,
                **self.config.__dict__, **checksum}


def checkpoint_snapshot_data(model: Any, path: "str | Path") -> SnapshotData:
    """The data a checkpoint was trained with (its recorded data settings), on its dataset file at `path`
    (found by :func:`lnf.evaluation_pipeline.checkpoint_data`; only read there if outside the data folder), prepared."""
    record = {k: v for k, v in model.checkpoint["data"].items() if k != "checksum"}
    dm = SnapshotData(scene=model.scene, **{**record, "path": str(path), "explicit_path": True})
    dm.prepare_data()
    return dm
