"""A batch of snapshots, typed: what the data module yields and the training step reads."""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Mapping, Optional, Sequence

import torch
from torch import Tensor


@dataclass
class SnapshotBatch:
    """B snapshots of masked coarse observations, float32.

    points (B, Nobs, dim_B); values, velocities (B, Nobs, A); potential (B,): each snapshot's full-order potential
    energy V (the energy loss's target), or None when the model has no energy loss; gradients (B, Nobs, A, dim_B):
    the full-order ∇_X q at the observed points (the gradient loss's target), or None; accelerations (B, Nobs, A)
    and acceleration_valid (B,) bool: the observed acceleration field (finite differences of the observed
    velocities in time) and whether a snapshot has one (the dynamics-residual loss's target), or None.
    """

    points: Tensor
    values: Tensor
    velocities: Tensor
    potential: Optional[Tensor] = None
    gradients: Optional[Tensor] = None
    accelerations: Optional[Tensor] = None
    acceleration_valid: Optional[Tensor] = None

    def __len__(self) -> int:
        return self.values.shape[0]

    @classmethod
    def collate(cls, items: Sequence[Mapping[str, Tensor]]) -> "SnapshotBatch":
        """Stack the items of a :class:`lnf.dataset.snapshots.SnapshotDataset` (dicts holding the fields they
        carry; every item of a dataset carries the same ones)."""
        names = [f.name for f in fields(cls)]
        return cls(**{k: torch.stack([item[k] for item in items]) for k in names if k in items[0]})
