"""Black-box latent dynamics on neural-field codes (the CORAL / DINo family), for comparison.

Same modulated SIREN and K-step reduction as our model, but the latent dynamics q̃̈ = f_θ(q̃, q̃̇) are an
MLP fitted, after the field, to the codes of the training trajectories (q̃ = ρ̃(q(t)), q̃̇ = (dφ)^† q̇(t))
by multi-step RK4 rollouts; no Lagrangian structure. Energies are still measured through the
pulled-back Lagrangian, so energy drift compares like with like.
"""
from __future__ import annotations

import logging
import math
import time
from typing import Any

import torch
from torch import Tensor, nn

from lnf.dynamics_kind import LEARNED
from lnf.integrators.rk4 import RK4
from lnf.utils import require

log = logging.getLogger("lnf.latent_mlp")


class LearnedLatentDynamics:
    """Integrator-facing wrapper: acceleration from the MLP, energies from the pulled-back Lagrangian."""

    kind = LEARNED

    def __init__(self, mlp: "LatentMLPDynamics", lagrangian: Any) -> None:
        self.mlp, self.lagrangian = mlp, lagrangian

    def acceleration(self, q: Tensor, v: Tensor, t: float = 0.0) -> Tensor:
        return self.mlp(q, v)

    def energies(self, q: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        return self.lagrangian.energies(q, v)


class LatentMLPDynamics(nn.Module):
    """q̃̈ = f_θ(q̃, q̃̇), an MLP (SiLU) on standardised inputs.

    Args:
        latent_dim: d (set by the model).
        width, depth: hidden width and number of hidden layers.
        iterations, lr, batch_size: Adam steps (cosine schedule), learning rate, windows per step.
        window: steps of each multi-step RK4 rollout in the fitting loss.
        seed: seed of the initialisation and window sampling.
    """

    kind = LEARNED

    def __init__(self, latent_dim: int, width: int = 64, depth: int = 2, iterations: int = 2000, lr: float = 3e-3,
                 batch_size: int = 256, window: int = 8, seed: int = 0) -> None:
        super().__init__()
        for key, value, low in [("width", width, 1), ("depth", depth, 1), ("iterations", iterations, 0),
                                ("batch_size", batch_size, 1), ("window", window, 1)]:
            require(f"dynamics.{key}", value)
        require("dynamics.lr", lr)
        self.latent_dim = int(latent_dim)
        self.iterations, self.lr, self.batch_size, self.window, self.seed = int(iterations), float(lr), int(
            batch_size), int(window), int(seed)
        gen = torch.Generator().manual_seed(self.seed)
        layers: list[nn.Module] = []
        n_in = 2 * self.latent_dim
        for _ in range(int(depth)):
            layers += [nn.Linear(n_in, int(width)), nn.SiLU()]
            n_in = int(width)
        layers.append(nn.Linear(n_in, self.latent_dim))
        self.net = nn.Sequential(*layers)
        with torch.no_grad():
            for p in self.net.parameters():  # seeded init, independent of the global RNG
                p.copy_(torch.empty_like(p).uniform_(-1, 1, generator=gen) / math.sqrt(max(p.shape[-1], 1)))
        for name in ("q_mean", "q_std", "v_mean", "v_std", "a_scale"):
            self.register_buffer(name, torch.zeros(self.latent_dim) if "mean" in name else torch.ones(self.latent_dim))
        self.register_buffer("fitted", torch.tensor(False))

    def forward(self, q: Tensor, v: Tensor) -> Tensor:
        x = torch.cat([(q - self.q_mean) / self.q_std, (v - self.v_mean) / self.v_std], dim=-1)
        return self.net(x.to(self.q_mean.dtype)).to(q.dtype) * self.a_scale.to(q.dtype)

    def as_dynamics(self, lagrangian: Any) -> LearnedLatentDynamics:
        if not bool(self.fitted):
            raise RuntimeError("the latent MLP dynamics are not fitted: python -m lnf.train fits them after the field "
                               "and writes them to checkpoints/last.ckpt (load that checkpoint)")
        return LearnedLatentDynamics(self, lagrangian)

    def fit(self, q: Tensor, v: Tensor, dt: float) -> dict[str, float]:
        """Fit to latent trajectories q, v (n, T, d) sampled every `dt` [s]; returns the final losses."""
        if q.ndim != 3 or q.shape != v.shape or q.shape[-1] != self.latent_dim:
            raise ValueError(f"latent trajectories must be (n, T, {self.latent_dim}) each, got {tuple(q.shape)}, "
                             f"{tuple(v.shape)}")
        n, T, d = q.shape
        w = min(self.window, T - 1)
        if w < 1:
            raise ValueError("fitting latent dynamics needs trajectories of at least 2 samples")
        q, v = q.detach().to(self.q_mean), v.detach().to(self.q_mean)
        with torch.no_grad():
            self.q_mean.copy_(q.mean((0, 1)))
            self.q_std.copy_(q.std((0, 1)).clamp_min(1e-6))
            self.v_mean.copy_(v.mean((0, 1)))
            self.v_std.copy_(v.std((0, 1)).clamp_min(1e-6))
            self.a_scale.copy_(((v[:, 1:] - v[:, :-1]) / dt).std((0, 1)).clamp_min(1e-6))
        starts = torch.cartesian_prod(torch.arange(n), torch.arange(T - w))  # (n_windows, 2)
        gen = torch.Generator().manual_seed(self.seed)
        opt = torch.optim.Adam(self.net.parameters(), lr=self.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(self.iterations, 1))
        rk4 = RK4()
        dyn = LearnedLatentDynamics(self, None)
        offsets = torch.arange(1, w + 1)
        t0, loss_value = time.perf_counter(), float("nan")
        for it in range(self.iterations):
            idx = starts[torch.randint(len(starts), (min(self.batch_size, len(starts)),), generator=gen)]
            i, k = idx[:, 0], idx[:, 1]
            state = (q[i, k], v[i, k])
            loss = q.new_zeros(())
            for s in range(w):
                state = rk4.step(dyn, state, dt, 0.0)
                tq, tv = q[i, k + offsets[s]], v[i, k + offsets[s]]
                loss = loss + (((state[0] - tq) / self.q_std) ** 2).mean() + (((state[1] - tv) / self.v_std) ** 2).mean()
            loss = loss / w
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            loss_value = float(loss.detach())
            if it % max(self.iterations // 5, 1) == 0 or it == self.iterations - 1:
                log.info("latent MLP fit %d/%d: loss %.3e", it + 1, self.iterations, loss_value)
        self.fitted.fill_(True)
        return {"latent_fit_loss": loss_value, "latent_fit_seconds": time.perf_counter() - t0}


@torch.no_grad()
def latent_trajectories(model: Any, points: Tensor, values: Tensor, velocities: Tensor) -> tuple[Tensor, Tensor]:
    """Codes and code velocities (n, T, d) of observed trajectories: points (n, Nobs, dim_B), values and
    velocities (n, T, Nobs, A), through the model's reduction ρ̃ and (dφ)^†."""
    qs, vs = [], []
    for i in range(points.shape[0]):
        codes = model.reduce(points[i], values[i])
        qs.append(codes)
        vs.append(model.project_velocity(codes, points[i], velocities[i]))
    return torch.stack(qs), torch.stack(vs)
