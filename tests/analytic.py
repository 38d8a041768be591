"""Hand-written embeddings with known reduced dynamics, shared by tests."""
from __future__ import annotations

import torch

from lnf.siren import FieldJet


class LinearModeEmbedding:
    """φ(q̃, X) = u(X) q̃ for the lifted pendulum: M̃ = mℓ², c̃ = 0, g̃ = m g ℓ sin q̃ (docs/method.md §7.1)."""

    def __init__(self, scene, dtype=torch.float64):
        self.scene, self.dtype = scene, dtype
        self._modes = {}  # points are fixed: evaluate the mode once (also keeps numpy out of torch.func transforms)

    def jet(self, q, points, order=1, spatial=False):
        key = (tuple(points.shape), points.data_ptr())
        if key not in self._modes:
            self._modes[key] = torch.as_tensor(self.scene.mode(points.double().numpy()))
        u = self._modes[key].to(q.dtype)
        B, N = q.shape[0], u.shape[0]
        value = (q[:, None, :] * u[None, :, None])  # (B, N, 1)
        J = u[None, :, None, None].expand(B, N, 1, 1)
        H = torch.zeros(B, N, 1, 1, 1, dtype=q.dtype)
        return FieldJet(value=value, J=J if order >= 1 else None, H=H if order >= 2 else None)


class NonlinearEmbedding:
    """φ(q̃, X) = Σ_k a_k(X) f_k(q̃) with f = (sin q1, q1·q2, q2², cos q2): closed-form J and H (d = 2)."""

    def __init__(self, n_points: int, seed: int = 0):
        g = torch.Generator().manual_seed(seed)
        self.a = torch.randn(n_points, 4, generator=g, dtype=torch.float64)

    def jet(self, q, points, order=1, spatial=False):
        q1, q2 = q[:, 0], q[:, 1]
        z = torch.zeros_like(q1)
        f = torch.stack([torch.sin(q1), q1 * q2, q2**2, torch.cos(q2)], -1)  # (B, 4)
        df = torch.stack([torch.stack([torch.cos(q1), z], -1), torch.stack([q2, q1], -1),
                          torch.stack([z, 2 * q2], -1), torch.stack([z, -torch.sin(q2)], -1)], 1)  # (B,4,2)
        one = torch.ones_like(q1)
        ddf = torch.zeros(q.shape[0], 4, 2, 2, dtype=q.dtype)
        ddf[:, 0, 0, 0] = -torch.sin(q1)
        ddf[:, 1, 0, 1] = ddf[:, 1, 1, 0] = one
        ddf[:, 2, 1, 1] = 2 * one
        ddf[:, 3, 1, 1] = -torch.cos(q2)
        value = torch.einsum("nk,bk->bn", self.a, f)[..., None]
        J = torch.einsum("nk,bki->bni", self.a, df)[:, :, None, :]
        H = torch.einsum("nk,bkij->bnij", self.a, ddf)[:, :, None]
        return FieldJet(value=value, J=J, H=H)


class ModeMapEmbedding:
    """φ(q̃, X) = Σ_i u_i(X) f_i(q̃) for modes u (m, N) and a map f: ℝ^d → ℝ^m with closed-form jet.

    f = identity when `nonlinear` is False; else f(q̃) = (q1 + 0.3 q2², q2 + 0.2 sin q1) (d = m = 2).
    """

    def __init__(self, mode_values, nonlinear: bool = False):
        self.mode_values, self.nonlinear = mode_values, nonlinear

    def map(self, q):
        if not self.nonlinear:
            return q
        return torch.stack([q[:, 0] + 0.3 * q[:, 1] ** 2, q[:, 1] + 0.2 * torch.sin(q[:, 0])], -1)

    def jet(self, q, points, order=1, spatial=False):
        u = torch.as_tensor(self.mode_values(points.double().numpy()), dtype=q.dtype)  # (m, N)
        B, d = q.shape
        f = self.map(q)
        df = torch.eye(d, dtype=q.dtype).expand(B, d, d).clone()
        ddf = torch.zeros(B, d, d, d, dtype=q.dtype)
        if self.nonlinear:
            df[:, 0, 1] = 0.6 * q[:, 1]
            df[:, 1, 0] = 0.2 * torch.cos(q[:, 0])
            ddf[:, 0, 1, 1] = 0.6
            ddf[:, 1, 0, 0] = -0.2 * torch.sin(q[:, 0])
        value = torch.einsum("mn,bm->bn", u, f)[..., None]
        J = torch.einsum("mn,bmi->bni", u, df)[:, :, None, :]
        H = torch.einsum("mn,bmij->bnij", u, ddf)[:, :, None]
        return FieldJet(value=value, J=J if order >= 1 else None, H=H if order >= 2 else None)
