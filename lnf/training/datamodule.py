"""SnapshotDataModule: lnf.train's Lightning data module, the loaders over :class:`lnf.dataset.snapshots.SnapshotData`."""
from __future__ import annotations

import multiprocessing as mp
from typing import Optional

import lightning.pytorch as pl
from torch.utils.data import DataLoader

from lnf.dataset.snapshots import SnapshotData
from lnf.training.batch import SnapshotBatch
from lnf.training.sampling import GlobalBatchSampler


def worker_context() -> Optional[str]:
    """Start method of DataLoader workers: the default one, or "fork" (POSIX) / "spawn" inside a process
    whose default is foreign (a joblib loky worker of the local parallel launcher: torch's workers cannot
    start under "loky")."""
    method = mp.get_start_method(allow_none=True)
    if method in (None, "fork", "spawn", "forkserver"):
        return None
    return "fork" if "fork" in mp.get_all_start_methods() else "spawn"


class SnapshotDataModule(SnapshotData, pl.LightningDataModule):
    """:class:`SnapshotData` (its arguments, its file handling) with the DataLoaders of lnf.train: the training batches
    shared among DDP ranks, the validation and test splits whole on every rank."""

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        """Training batches are shared among DDP ranks (:class:`GlobalBatchSampler`); every rank evaluates
        the whole validation and test splits, so their losses equal the single-process ones."""
        dataset = self.snapshots(split)
        rank, world = (self.trainer.global_rank, self.trainer.world_size) if shuffle and self.trainer else (0, 1)
        sampler = GlobalBatchSampler(len(dataset), self.batch_size, shuffle=shuffle, seed=self.shuffle_seed,
                                     drop_last=shuffle and len(dataset) > self.batch_size, rank=rank, world_size=world)
        return DataLoader(dataset, batch_size=sampler.per_rank_batch_size, sampler=sampler,
                          collate_fn=SnapshotBatch.collate, num_workers=self.num_workers, persistent_workers=self.num_workers > 0,
                          multiprocessing_context=worker_context() if self.num_workers > 0 else None)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", False)
