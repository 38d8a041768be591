"""A field that meets its scene's clamp exactly: φ(q̃, X) = s(X) ψ(q̃, X), s = 0 on the clamped boundary.

A SIREN fitted to values leaves a small, wiggly field where the body is clamped, and its gradient there
becomes spurious strain energy in the pulled-back potential (eq. 11). Multiplying by a factor s that
vanishes on the clamp (the scene's ``clamp_factor``, e.g. s = X₁/L for a cantilever clamped at X₁ = 0) makes
φ = 0 there for every q̃, as the standard distance-function construction of essential boundary conditions
does. The jet follows from the product rule (s does not depend on q̃):

    J = s J_ψ,  H = s H_ψ,  G = s G_ψ + ψ ⊗ ∇s,  GJ = s GJ_ψ + J_ψ ⊗ ∇s.
"""
from __future__ import annotations

from typing import Callable

from torch import Tensor, nn

from lnf.siren import FieldJet

ClampFactor = Callable[[Tensor], "tuple[Tensor, Tensor]"]  # points (…, N, dim_B) → s (…, N), ∇s (…, N, dim_B)


class ClampedField(nn.Module):
    """φ = s(X) ψ(q̃, X) for a field ψ with ``__call__``/``jet`` (e.g. :class:`lnf.siren.ModulatedSiren`)."""

    def __init__(self, field: nn.Module, factor: ClampFactor) -> None:
        super().__init__()
        self.field = field
        self.factor = factor

    @property
    def latent_dim(self) -> int:
        return self.field.latent_dim

    @property
    def depth(self) -> int:
        """Sine layers of the wrapped field."""
        return self.field.depth

    def forward(self, codes: Tensor, points: Tensor) -> Tensor:
        """φ(q̃, X): codes (B, d), points (N, dim_B) or (B, N, dim_B) → values (B, N, dim_A)."""
        s, _ = self.factor(points)
        return s[..., None] * self.field(codes, points)

    def jet(self, codes: Tensor, points: Tensor, order: int = 1, spatial: bool = False) -> FieldJet:
        """φ and its derivatives (shapes as :meth:`lnf.siren.ModulatedSiren.jet`)."""
        inner = self.field.jet(codes, points, order=order, spatial=spatial)
        s, ds = self.factor(points)
        s_a = s[..., None]  # (…, N, 1): broadcasts over the field components
        out = FieldJet(value=s_a * inner.value)
        if inner.J is not None:
            out.J = s_a[..., None] * inner.J
        if inner.H is not None:
            out.H = s_a[..., None, None] * inner.H
        if inner.G is not None:  # (B, N, A, dim_B)
            out.G = s_a[..., None] * inner.G + inner.value[..., None] * ds[..., None, :]
        if inner.GJ is not None:  # (B, N, A, dim_B, d)
            out.GJ = s_a[..., None, None] * inner.GJ + inner.J[..., None, :] * ds[..., None, :, None]
        return out


def is_clamped(model: object) -> bool:
    """Whether `model`'s field is clamped (``model.clamp=true``: a :class:`ClampedField`)."""
    return isinstance(getattr(model, "field", None), ClampedField)
