"""DataModule: generates/validates the HDF5 dataset and serves masked coarse snapshots."""
from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import Any, Optional

import lightning.pytorch as pl
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from lnf.dataset import DatasetConfig, TrajectorySplit, ensure_dataset, generation_attributes, load_split
from lnf.model import build
from lnf.scenes.base import Scene

log = logging.getLogger("lnf.data")


class SnapshotDataset(Dataset):
    """Snapshots (trajectory i, time k) of each trajectory's own masked coarse observations.

    Built from points (n, Nobs, dim_B), values and velocities (n, T', Nobs, A) (see
    :meth:`SnapshotDataModule.observations`). Item: points (Nobs, dim_B), values (Nobs, A), velocities (Nobs, A).
    """

    def __init__(self, points: np.ndarray, values: np.ndarray, velocities: np.ndarray) -> None:
        self.points = torch.as_tensor(points, dtype=torch.float32)
        self.values = torch.as_tensor(values, dtype=torch.float32)
        self.velocities = torch.as_tensor(velocities, dtype=torch.float32)
        self.n_times = self.values.shape[1]

    def __len__(self) -> int:
        return self.values.shape[0] * self.n_times

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        i, k = divmod(int(index), self.n_times)
        return self.points[i], self.values[i, k], self.velocities[i, k]


def default_path(data_dir: str | Path, scene: Scene, cfg: DatasetConfig) -> Path:
    """``{data_dir}/{scene.name}-{hash of the generation attributes}.h5``: one file per parameter set."""
    attrs = json.dumps(generation_attributes(scene, cfg), sort_keys=True, default=str)
    return Path(data_dir) / f"{scene.name}-{hashlib.sha1(attrs.encode()).hexdigest()[:10]}.h5"


class SnapshotDataModule(pl.LightningDataModule):
    """Args: scene (object or spec), data_dir, path (None → :func:`default_path`), on_mismatch
    ('regenerate' | 'error'), batch_size, num_workers, noise (std of Gaussian noise added to the observed
    training values and velocities, relative to their RMS over the split; seeded by `seed`), and the
    :class:`DatasetConfig` fields."""

    def __init__(self, scene: "Scene | dict", data_dir: str = "data", path: Optional[str] = None,
                 on_mismatch: str = "regenerate", batch_size: int = 32, num_workers: int = 0,
                 noise: float = 0.0, **generation: Any) -> None:
        super().__init__()
        self.scene = build(scene) if isinstance(scene, dict) else scene
        self.config = DatasetConfig.from_mapping(generation)
        self.path = Path(path) if path else default_path(data_dir, self.scene, self.config)
        self.on_mismatch = on_mismatch
        if int(batch_size) != batch_size or batch_size < 1:
            raise ValueError(f"data.batch_size must be an integer ≥ 1, got {batch_size!r}")
        self.batch_size, self.num_workers = int(batch_size), int(num_workers)
        if not (np.isfinite(noise) and noise >= 0):
            raise ValueError(f"data.noise must be a finite number ≥ 0 (relative noise std), got {noise!r}")
        self.noise = float(noise)
        self._splits: dict[str, TrajectorySplit] = {}

    def prepare_data(self) -> None:
        ensure_dataset(self.scene, self.config, self.path, on_mismatch=self.on_mismatch)

    def split(self, name: str) -> TrajectorySplit:
        """The validated split ('train', 'val', 'test'), loaded once."""
        if name not in self._splits:
            self._splits[name] = load_split(self.path, name, scene=self.scene, cfg=self.config)
        return self._splits[name]

    def setup(self, stage: Optional[str] = None) -> None:
        self.prepare_data()

    def observations(self, split: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What a model may learn from: each trajectory's masked coarse points (n, Nobs, dim_B), values and
        velocities (n, T', Nobs, A) over the first `train_times` samples, with `noise` added to the training split."""
        points, values, velocities = self.split(split).observed(self.config.train_times, velocities=True)
        if self.noise > 0 and split == "train":
            rng = np.random.default_rng(self.config.seed + 7919)
            for arr in (values, velocities):
                rms = float(np.sqrt(np.mean(arr.astype(np.float64) ** 2)))
                arr += (self.noise * rms * rng.standard_normal(arr.shape)).astype(arr.dtype)
        return points, values, velocities

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        ds = SnapshotDataset(*self.observations(split))
        return DataLoader(ds, batch_size=self.batch_size, shuffle=shuffle, num_workers=self.num_workers,
                          drop_last=shuffle and len(ds) > self.batch_size, persistent_workers=self.num_workers > 0)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", False)

    def describe(self) -> dict[str, Any]:
        """Data settings to store in checkpoints (enough to regenerate the same file)."""
        return {"path": str(self.path), "on_mismatch": self.on_mismatch, **self.config.__dict__}

    def describe_observations(self) -> dict[str, Any]:
        """How the training observations were corrupted (kept beside :meth:`describe` in checkpoints)."""
        return {"noise": self.noise}
