"""What an evaluation will cost before it runs: frames, points, memory, decoding blocks (printed first)."""
from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import torch
from torch import Tensor

from lnf.reduced_model import ReducedModel
from lnf.quadrature import Quadrature, QuadratureRule

log = logging.getLogger("lnf.evaluation")


# Memory bounds of an evaluation (see :func:`evaluate_rollouts`): the true fields of a block of frames in float64
# take at most FRAME_BLOCK_BYTES (the block's predicted and projected fields as much again), one decoding batch
# at most DECODE_FRAME_POINTS (frame, point) pairs of φ's activations, and one energy evaluation at most
# ENERGY_STATE_POINTS (reduced state, quadrature point) pairs of φ's first-order jet.
FRAME_BLOCK_BYTES = 64 * 2 ** 20


DECODE_FRAME_POINTS = 2 ** 18


ENERGY_STATE_POINTS = 2 ** 17


def decode_batch(n_points: int, snapshot_chunk: int = 32, max_frame_points: int = DECODE_FRAME_POINTS) -> int:
    """Frames decoded (and reduced) per batch: `snapshot_chunk`, fewer on many points (32 frames × 16384 points held
    about 0.7 GB of activations at width 64), at least one."""
    return max(1, min(int(snapshot_chunk), int(max_frame_points) // max(int(n_points), 1)))


def frame_block(n_points: int, field_dim: int, snapshot_chunk: int = 32,
                budget_bytes: int = FRAME_BLOCK_BYTES) -> int:
    """Frames decoded and compared at once: as many as fit `budget_bytes` of float64 fields (N, A) each, a multiple
    of `snapshot_chunk` (the decoding batch), at least one batch."""
    per_frame = max(int(n_points) * int(field_dim) * 8, 1)
    frames = max(int(budget_bytes) // per_frame, 1)
    return max(int(snapshot_chunk), frames // int(snapshot_chunk) * int(snapshot_chunk))


def quadrature_size(model: ReducedModel, quadrature: "Quadrature | QuadratureRule | None" = None) -> int:
    """Points of the quadrature the reduced dynamics (and the reduced energies) sum over."""
    rule = quadrature if quadrature is not None else model.quadrature_rule
    quad = rule if isinstance(rule, Quadrature) else rule.build_for(model.scene)
    return int(quad.points.shape[0])


@dataclass
class EvaluationCost:
    """What an evaluation holds and computes: n trajectories × T frames × N points × A components."""

    trajectories: int
    frames: int
    points: int
    field_dim: int
    kept_trajectories: int
    block_frames: int
    quadrature_points: Optional[int] = None
    trained_quadrature_points: Optional[int] = None  # the checkpoint's own rule, when another one is evaluated
    substeps: int = 1  # integration steps per frame (integrator.substeps)
    state_dim: int = 0  # S of the full-order states held (n, T, S); 0 where none are
    latent_dim: int = 1
    body_dim: int = 1  # coordinates per evaluation point
    long_trajectories: int = 0  # the long-horizon energy check: trajectories × long_steps, recorded every 10th
    long_steps: int = 0
    record_every: int = 10

    @property
    def rollout_steps(self) -> int:
        """Integration steps of each trajectory's rollout: (frames − 1) × substeps (batched over trajectories)."""
        return max(self.frames - 1, 0) * self.substeps

    @property
    def long_rollout_steps(self) -> int:
        """Integration steps of the long-horizon energy check: long_steps × substeps."""
        return self.long_steps * self.substeps

    @property
    def rollout_memory_bytes(self) -> int:
        """About what the evaluation of the rollouts holds at most, besides the model: :attr:`peak_bytes` of fields,
        the evaluation points (float64 and float32 copies), the full-order states (n, T, S) in float64 (twice, while
        simulated), the reduced trajectories and references (n, T, d) in a few copies and a dozen per-frame
        arrays (n, T) in float64 (errors, norms, energies)."""
        frames = self.trajectories * self.frames
        return (self.peak_bytes + 16 * self.points * self.body_dim + 8 * self.frames
                + 16 * frames * self.state_dim + 48 * frames * self.latent_dim + 128 * frames)

    @property
    def long_memory_bytes(self) -> int:
        """About what the long-horizon energy check holds: its recorded states (q̃, q̃̇ and copies) and energies."""
        records = self.long_steps // max(self.record_every, 1) + 1
        return self.long_trajectories * records * (32 * self.latent_dim + 48)

    @property
    def memory_bytes(self) -> int:
        """The larger of the two parts (they run one after the other): what :func:`lnf.evaluate` checks against the
        memory it may use."""
        return max(self.rollout_memory_bytes, self.long_memory_bytes)

    @property
    def field_bytes(self) -> int:
        """All predicted fields (n, T, N, A) in float32: what holding them at once would take."""
        return self.trajectories * self.frames * self.points * self.field_dim * 4

    @property
    def peak_bytes(self) -> int:
        """About what the chunked evaluation holds at most: the kept trajectories' predicted and true fields
        (float64) and one block of true, predicted and projected fields (float64 and float32 copies)."""
        kept = 2 * self.kept_trajectories * self.frames * self.points * self.field_dim * 8
        return kept + 5 * self.block_frames * self.points * self.field_dim * 8

    @property
    def unchunked_bytes(self) -> int:
        """What the evaluation held before it was chunked: predicted, projected and true fields of every trajectory
        in float64, with float32 copies of the first two."""
        return self.trajectories * self.frames * self.points * self.field_dim * (3 * 8 + 2 * 4)

    def describe(self) -> str:
        quad = f"; the reduced dynamics sum over {self.quadrature_points} quadrature points per evaluation" \
            if self.quadrature_points else ""
        if self.quadrature_points and self.trained_quadrature_points not in (None, self.quadrature_points):
            ratio = self.quadrature_points / self.trained_quadrature_points
            quad += (f" (the checkpoint's rule has {self.trained_quadrature_points}: the rollout costs about "
                     f"{ratio:.3g}× as much)")
        steps = (f"; the rollout takes {self.rollout_steps} integration steps per trajectory ({self.frames - 1} "
                 f"sample intervals × integrator.substeps={self.substeps})")
        long = (f"; the long-horizon check {self.long_rollout_steps} steps ({self.long_steps} × {self.substeps}) of "
                f"{self.long_trajectories} trajector{'y' if self.long_trajectories == 1 else 'ies'}"
                if self.long_steps > 0 and self.long_trajectories > 0 else "")
        return (f"{self.trajectories} trajectories × {self.frames} frames × {self.points} points"
                f"{f' × {self.field_dim} components' if self.field_dim > 1 else ''}: the predicted fields are "
                f"{_size(self.field_bytes)} in float32 (the true and projected ones as much again); decoded "
                f"{self.block_frames} frames at a time, keeping the fields of {self.kept_trajectories} "
                f"trajector{'y' if self.kept_trajectories == 1 else 'ies'}: about {_size(self.peak_bytes)} at most "
                f"({_size(self.memory_bytes)} with the states, codes and energies){steps}{long}{quad}")


def size_text(n_bytes: float) -> str:
    """A size in words: 512 B, 1.5 KB, 43.2 MB, 7.1 GB (GB however large)."""
    return _size(n_bytes)


def _size(n_bytes: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n_bytes < 1024 or unit == "GB":
            return f"{n_bytes:.0f} {unit}" if unit == "B" else f"{n_bytes:.1f} {unit}"
        n_bytes /= 1024
    return f"{n_bytes:.1f} TB"  # pragma: no cover


def evaluation_cost(n: int, frames: int, n_points: int, field_dim: int, keep_fields: Optional[int] = None,
                    snapshot_chunk: int = 32, quadrature_points: Optional[int] = None,
                    trained_quadrature_points: Optional[int] = None, substeps: int = 1, state_dim: int = 0,
                    latent_dim: int = 1, body_dim: int = 1, long_trajectories: int = 0,
                    long_steps: int = 0) -> EvaluationCost:
    """The :class:`EvaluationCost` of :func:`evaluate_rollouts` (and of a :func:`long_horizon_energy` check of
    `long_trajectories` × `long_steps`) with these sizes, each step taken as `substeps` integration steps (printed
    and checked by ``lnf.evaluate`` before it loads data or rolls out). Plain integer arithmetic: sizes too large
    to allocate are described, not allocated."""
    keep = n if keep_fields is None else min(max(int(keep_fields), 0), n)
    block = min(frame_block(n_points, field_dim, decode_batch(n_points, snapshot_chunk)), max(n * frames, 1))
    return EvaluationCost(n, frames, n_points, field_dim, keep, block, quadrature_points, trained_quadrature_points,
                          int(substeps), int(state_dim), int(latent_dim), int(body_dim), int(long_trajectories),
                          int(long_steps))


def chunked_energy(model: ReducedModel, q: Tensor, v: Tensor, quadrature: "Quadrature | QuadratureRule | None" = None,
                   max_state_points: int = ENERGY_STATE_POINTS) -> tuple[Tensor, Tensor]:
    """``model.energy(q, v, quadrature)`` of states (M, d) in batches of at most `max_state_points` / (quadrature
    points) states: the jet of φ over every state and quadrature point at once needed (M · points · width) floats
    (13.8 GB for 1600 states on a 64² uniform rule). One batch, as before, when it fits."""
    per = max(int(max_state_points) // max(quadrature_size(model, quadrature), 1), 1)
    if q.shape[0] <= per:
        return model.energy(q, v, quadrature)
    parts = [model.energy(q[i:i + per], v[i:i + per], quadrature) for i in range(0, q.shape[0], per)]
    return torch.cat([k for k, _ in parts]), torch.cat([u for _, u in parts])


MEMORY_ENV = "LNF_MAX_MEMORY_GB"  # the memory lnf.evaluate may use [GB], where max_memory_gb is null
GB = 2 ** 30


def _meminfo_available() -> Optional[int]:
    """MemAvailable of /proc/meminfo [bytes] (Linux), None elsewhere."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cgroup_room() -> Optional[int]:
    """Bytes left under this process's cgroup memory limit (v2 memory.max, v1 limit_in_bytes), None without one."""
    for limit, usage in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                         ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            text = Path(limit).read_text().strip()
            if text == "max" or int(text) >= 2 ** 60:  # no limit
                continue
            return max(int(text) - int(Path(usage).read_text().strip()), 0)
        except (OSError, ValueError):
            continue
    return None


def available_memory() -> tuple[Optional[int], str]:
    """The memory [bytes] this process may still allocate, and where the figure comes from: MemAvailable of
    /proc/meminfo (lowered to the room under a cgroup memory limit), else os.sysconf's available pages (physical
    pages where the system has no count of available ones); (None, why) where none can be read."""
    found = [(v, where) for v, where in ((_meminfo_available(), "MemAvailable of /proc/meminfo"),
                                         (_cgroup_room(), "the room under the cgroup memory limit")) if v is not None]
    if found:
        return min(found)
    for pages, where in (("SC_AVPHYS_PAGES", "available"), ("SC_PHYS_PAGES", "physical")):
        try:
            return int(os.sysconf(pages)) * int(os.sysconf("SC_PAGE_SIZE")), f"the machine's {where} memory (os.sysconf)"
        except (ValueError, OSError, AttributeError):
            continue
    return None, "the available memory could not be read"


def memory_limit(max_memory_gb: Optional[float] = None) -> tuple[Optional[int], str]:
    """The memory [bytes] an evaluation may hold and what set it: max_memory_gb, else $LNF_MAX_MEMORY_GB, else the
    memory available now (:func:`available_memory`; None where it cannot be read)."""
    if max_memory_gb is not None:
        return int(float(max_memory_gb) * GB), f"max_memory_gb={max_memory_gb}"
    env = os.environ.get(MEMORY_ENV, "").strip()
    if env:
        try:
            value = float(env)
        except ValueError:
            value = float("nan")
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"${MEMORY_ENV}={env!r} must be a finite number > 0 [GB] (the memory lnf.evaluate may "
                             f"use); unset it to use the memory available now")
        return int(value * GB), f"${MEMORY_ENV}={env}"
    found, where = available_memory()
    return found, f"the memory available now, {where}; set max_memory_gb=<GB> or ${MEMORY_ENV} to change it"
