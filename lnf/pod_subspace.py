"""An embedding that contains the POD subspace: φ(q̃, X) = m(X) + Φ(X) q̃ + ψ(q̃, X) (``model.pod_subspace=true``).

m and Φ are the mean and first d POD modes of the training observations (:func:`lnf.baselines.pod.fit_pod`, fixed
once fitted), every mode scaled by the spread of the first one's coefficients: the first code has unit variance and
the modes keep their L² orthogonality and equal norms, so the pulled-back mass of the linear part is a multiple of the
identity (scaled to unit variance each, M̃ had the condition number of the variances' ratio, and at d = 2 on the
cantilever the training bent it until every rollout diverged);
ψ is the SIREN (clamped where the model is), its output layer zero at initialisation and its output multiplied by a
fixed scale ε (``model.pod_residual_scale``): Adam moves every weight by about the learning rate per step whatever its
gradient, so with ε = 1 at the studies' learning rate (2e-3) ψ outgrew what the modes leave before training could shape
it; ε = 0.1 moves ψ as a learning rate ten times smaller would, and leaves the rest of the optimiser as it is. So
training starts from the
POD-Galerkin model of the same dimension, whose pulled-back dynamics are the intrusive linear ROM's, and the SIREN
learns the nonlinear correction: the linear basis plus a learned curved part of quadratic-manifold reduced models.
The reduction ρ̃ starts its K steps from the least-squares projection onto the POD modes.

The jet is the sum of the two: J = Φ + εJ_ψ, H = εH_ψ, G = ∇m + ∇Φ q̃ + εG_ψ, GJ = ∇Φ + εGJ_ψ.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

from lnf.baselines.pod import LinearEmbedding, fit_pod, frame_coefficients
from lnf.siren import FieldJet


class SubspacePlusField(nn.Module):
    """φ = linear(q̃, X) + ε residual(q̃, X): a :class:`LinearEmbedding` (the POD subspace) plus a field with the
    :class:`lnf.siren.ModulatedSiren` call and ``jet`` signature, scaled by `residual_scale` ε > 0."""

    #: the modes are scaled alike: a unit of any code is the same size of field (ReducedModel.code_span_floor)
    commensurate_codes = True

    def __init__(self, linear: LinearEmbedding, residual: nn.Module, residual_scale: float = 1.0) -> None:
        super().__init__()
        self.linear, self.residual = linear, residual
        self.residual_scale = float(residual_scale)
        self.register_buffer("fitted", torch.tensor(False))

    @property
    def latent_dim(self) -> int:
        return self.linear.latent_dim

    @property
    def depth(self) -> int:
        return self.residual.depth

    def forward(self, codes: Tensor, points: Tensor) -> Tensor:
        """φ(q̃, X): codes (B, d), points (N, dim_B) or (B, N, dim_B) → values (B, N, dim_A)."""
        return self.linear(codes, points) + self.residual_scale * self.residual(codes, points)

    def jet(self, codes: Tensor, points: Tensor, order: int = 1, spatial: bool = False) -> FieldJet:
        """φ and its derivatives (shapes as :meth:`lnf.siren.ModulatedSiren.jet`)."""
        a = self.linear.jet(codes, points, order=min(order, 1), spatial=spatial)
        b = self.residual.jet(codes, points, order=order, spatial=spatial)
        eps = self.residual_scale
        out = FieldJet(value=a.value + eps * b.value)
        out.J = None if b.J is None else a.J + eps * b.J
        out.H = None if b.H is None else eps * b.H  # the linear part has none
        out.G = None if b.G is None else a.G + eps * b.G
        out.GJ = None if b.GJ is None else a.GJ + eps * b.GJ
        return out

    def start(self, points: Tensor, values: Tensor, density: Tensor) -> Tensor:
        """The least-squares codes of `values` (B, N, A) on the POD subspace at `points`, weighted by ω0 (B, d)."""
        return self.linear.project(points, values, density)

    @torch.no_grad()
    def fit(self, points: "Tensor | np.ndarray", values: "Tensor | np.ndarray", ridge: float = 1e-12,
            max_condition: float = 1e3) -> dict[str, float]:
        """m and Φ from training observations: points (n, Nobs, dim_B), values (n, T, Nobs, A); every mode scaled by
        the first mode's coefficients' standard deviation over the n·T snapshots (the first code has unit variance)."""
        n, T = np.shape(values)[:2]
        coefficients = frame_coefficients(self.linear.basis, points, values, ridge, max_condition)
        mean, modes, s, info = fit_pod(self.linear.basis, self.latent_dim, coefficients)
        self.linear.set_subspace(mean, modes * (s[0] / math.sqrt(n * T)))
        self.fitted.fill_(True)
        return info

    @torch.no_grad()
    def take_fit(self, other: "SubspacePlusField") -> None:
        """m and Φ as `other` fitted them."""
        self.linear.set_subspace(other.linear.mean, other.linear.modes)
        self.fitted.copy_(other.fitted)


def zero_output(field: nn.Module) -> None:
    """Zero the output layer of a SIREN (or of the SIREN a :class:`lnf.boundary.ClampedField` wraps): ψ = 0."""
    inner = getattr(field, "field", field)
    with torch.no_grad():
        inner.out.weight.zero_()
        inner.out.bias.zero_()
