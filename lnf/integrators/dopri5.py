"""Adaptive Dormand–Prince 5(4) from torchdiffeq, for reference solutions."""
from __future__ import annotations

from typing import Callable, Optional

import torch
from torch import Tensor
from torchdiffeq import odeint

from lnf.integrators.base import Dynamics, Integrator, RolloutDivergedError, Trajectory, initial_state_cause
from lnf.utils import require


class Dopri5(Integrator):
    name = "dopri5"

    def __init__(self, rtol: float = 1e-9, atol: float = 1e-9, substeps: int = 1, max_abs: float = 1e6) -> None:
        super().__init__(substeps=substeps, max_abs=max_abs, max_substeps=1)  # adaptive: its own step control
        self.rtol, self.atol = require("integrator.rtol", rtol), require("integrator.atol", atol)

    def __repr__(self) -> str:
        return f"Dopri5(rtol={self.rtol:g}, atol={self.atol:g})"

    @torch.no_grad()
    def integrate(self, dynamics: Dynamics, q0: Tensor, v0: Tensor, dt: float, steps: int,
                  record_every: int = 1, t0: float = 0.0, on_divergence: str = "raise",
                  progress: Optional[Callable[[int], None]] = None) -> Trajectory:
        self._check_args(q0, v0, dt, steps, record_every, on_divergence)
        d = q0.shape[1]
        n_rec = steps // record_every + 1
        times = t0 + dt * record_every * torch.arange(n_rec, dtype=torch.float64)

        def rhs(t: Tensor, y: Tensor) -> Tensor:
            q, v = y[:, :d], y[:, d:]
            return torch.cat([v, dynamics.acceleration(q, v, float(t))], dim=-1)

        y0 = torch.cat([q0, v0], dim=-1)
        try:
            ys = odeint(rhs, y0, times.to(q0.dtype), rtol=self.rtol, atol=self.atol, method="dopri5")
        except AssertionError as err:  # torchdiffeq signals step-size underflow with an assertion
            rows = list(range(q0.shape[0]))
            raise RolloutDivergedError(-1, float("nan"), rows, self.name, dt,
                                       initial_state_cause(dynamics, q0, v0, rows, t0)) from err
        if progress is not None:  # torchdiffeq integrates the whole span in one call
            progress(steps)
        ys = ys.transpose(0, 1)  # (B, T, 2d)
        bad = ~torch.isfinite(ys).all(-1) | (ys.abs() > self.max_abs).any(-1)  # (B, T)
        diverged = torch.where(bad.any(-1), bad.float().argmax(-1) * record_every, -1)
        if bool(bad.any()):
            first = int(bad.float().argmax(-1)[bad.any(-1)].min())
            if on_divergence == "raise":
                rows = bad.any(-1).nonzero().flatten().tolist()
                raise RolloutDivergedError(first * record_every, float(times[first]), rows, self.name, dt,
                                           initial_state_cause(dynamics, q0, v0, rows, t0) if first <= 1 else None)
            ys = torch.where(bad.cumsum(-1)[..., None] > 0, float("nan"), ys)
        return Trajectory(times=times, q=ys[..., :d], v=ys[..., d:], diverged_step=diverged, steps=steps, dt=dt)
