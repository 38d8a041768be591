"""A sampler whose global batches do not depend on the number of processes or on restarts."""
from __future__ import annotations

from typing import Iterator

import torch
from torch.utils.data import Sampler


class GlobalBatchSampler(Sampler[int]):
    """Indices of one seeded permutation per epoch, cut into global batches and shared among ranks.

    Epoch e uses the permutation drawn from ``seed + e`` (or 0..n−1 without shuffling), cut into global
    batches of ``batch_size``; rank r of ``world_size`` yields its contiguous share of every global batch,
    ``batch_size // world_size`` indices, so a DataLoader with that per-rank batch size gives each rank
    its part of the same global batch. Hence:

    - under DDP (gradients averaged over ranks) the optimiser sees the same batches as one process;
    - a run resumed from a checkpoint at epoch e sees the same batches as an uninterrupted run.

    Lightning calls :meth:`set_epoch` before each epoch.

    Args:
        n: dataset size; batch_size: global batch size, divisible by world_size; shuffle; seed;
        drop_last: drop a last incomplete global batch (a last batch smaller than world_size is always
            dropped, since every rank must take the same number of steps); rank, world_size.
    """

    def __init__(self, n: int, batch_size: int, shuffle: bool = True, seed: int = 0, drop_last: bool = False,
                 rank: int = 0, world_size: int = 1) -> None:
        if world_size < 1 or not 0 <= rank < world_size:
            raise ValueError(f"rank must be in [0, world_size), got rank {rank}, world_size {world_size}")
        if batch_size < 1 or batch_size % world_size:
            raise ValueError(f"data.batch_size (the global batch) must be a positive multiple of the number of "
                             f"processes {world_size}, got {batch_size}")
        if n < world_size:
            raise ValueError(f"{n} snapshots cannot be shared among {world_size} processes")
        self.n, self.batch_size, self.shuffle, self.seed = int(n), int(batch_size), bool(shuffle), int(seed)
        self.drop_last, self.rank, self.world_size = bool(drop_last), int(rank), int(world_size)
        self.epoch = 0

    @property
    def per_rank_batch_size(self) -> int:
        return self.batch_size // self.world_size

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _batches(self) -> list[tuple[int, int]]:
        """(start, stop) of each global batch kept."""
        spans = [(start, min(start + self.batch_size, self.n)) for start in range(0, self.n, self.batch_size)]
        return [(a, b) for a, b in spans
                if b - a == self.batch_size or not (self.drop_last or b - a < self.world_size)]

    def _shares(self) -> list[tuple[int, int]]:
        """(lo, hi) positions in the epoch's order of this rank's share of each global batch kept."""
        return [(a + self.rank * (b - a) // self.world_size, a + (self.rank + 1) * (b - a) // self.world_size)
                for a, b in self._batches()]

    def __iter__(self) -> Iterator[int]:
        if self.shuffle:
            order = torch.randperm(self.n, generator=torch.Generator().manual_seed(self.seed + self.epoch))
        else:
            order = torch.arange(self.n)
        for lo, hi in self._shares():
            yield from order[lo:hi].tolist()

    def __len__(self) -> int:
        return sum(hi - lo for lo, hi in self._shares())
