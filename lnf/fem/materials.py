"""Hyperelastic materials: a stored energy W(F) and its first Piola–Kirchhoff stress P = ∂W/∂F, in torch.

One definition serves both sides of lnf: the pulled-back potential of a neural field evaluates W and P at
F = I + ∇_X φ (autograd flows through them), and the finite-element reference (:mod:`lnf.fem.body`) takes
P and the exact tangent moduli A = ∂P/∂F (by forward-mode differentiation of P, :meth:`tangent`) at its
quadrature points. F is (…, d, d) with d = 2 (plane strain) or 3; energies are per unit reference volume
(per unit area and depth in 2-D), in Pa = J/m³.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any

import torch
from torch import Tensor


def lame(young: float, poisson: float) -> tuple[float, float]:
    """(λ, μ) [Pa] from Young's modulus E [Pa] and Poisson's ratio ν ∈ [0, 0.5)."""
    if not (math.isfinite(young) and young > 0):
        raise ValueError(f"Young's modulus must be a finite number > 0 [Pa], got {young!r}")
    if not (math.isfinite(poisson) and 0 <= poisson < 0.5):
        raise ValueError(f"Poisson's ratio must be in [0, 0.5), got {poisson!r}")
    return young * poisson / ((1 + poisson) * (1 - 2 * poisson)), young / (2 * (1 + poisson))


def determinant(F: Tensor) -> Tensor:
    """det F (…) of (…, d, d), written out for d = 2, 3 (elementwise: far faster than a batched LU of tiny
    matrices)."""
    d = F.shape[-1]
    if d == 2:
        return F[..., 0, 0] * F[..., 1, 1] - F[..., 0, 1] * F[..., 1, 0]
    if d == 3:
        return (F[..., 0, 0] * (F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1])
                - F[..., 0, 1] * (F[..., 1, 0] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 0])
                + F[..., 0, 2] * (F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0]))
    return torch.linalg.det(F)


def cofactor(F: Tensor) -> Tensor:
    """cof F = det(F) F⁻ᵀ (…, d, d), written out for d = 2, 3 (defined for singular F too)."""
    d = F.shape[-1]
    if d == 2:
        return torch.stack([torch.stack([F[..., 1, 1], -F[..., 1, 0]], -1),
                            torch.stack([-F[..., 0, 1], F[..., 0, 0]], -1)], -2)
    if d == 3:
        rows = []
        for i in range(3):
            i1, i2 = (i + 1) % 3, (i + 2) % 3
            rows.append(torch.stack([F[..., i1, (j + 1) % 3] * F[..., i2, (j + 2) % 3]
                                     - F[..., i1, (j + 2) % 3] * F[..., i2, (j + 1) % 3] for j in range(3)], -1))
        return torch.stack(rows, -2)
    return determinant(F)[..., None, None] * torch.linalg.inv(F).transpose(-1, -2)


def _eye(F: Tensor) -> Tensor:
    return torch.eye(F.shape[-1], dtype=F.dtype, device=F.device)


class HyperelasticMaterial(ABC):
    """A compressible isotropic hyperelastic material with Lamé parameters λ, μ [Pa]."""

    name: str = ""
    #: W is the material's only for det F ≥ :attr:`min_jacobian` (the finite-element reference stops with an
    #: error below it: an element crushed or inverted)
    needs_positive_jacobian: bool = False
    min_jacobian: float = 0.0

    def __init__(self, lam: float, mu: float) -> None:
        if not (math.isfinite(lam) and math.isfinite(mu) and mu > 0 and lam >= 0):
            raise ValueError(f"{type(self).__name__}: Lamé parameters must be finite with μ > 0 and λ ≥ 0, "
                             f"got λ = {lam!r}, μ = {mu!r}")
        self.lam, self.mu = float(lam), float(mu)

    @classmethod
    def from_young_poisson(cls, young: float, poisson: float) -> "HyperelasticMaterial":
        return cls(*lame(young, poisson))

    @abstractmethod
    def energy_density(self, F: Tensor) -> Tensor:
        """W(F) [Pa] for deformation gradients F (…, d, d) → (…)."""

    @abstractmethod
    def first_piola(self, F: Tensor) -> Tensor:
        """P = ∂W/∂F [Pa] (…, d, d)."""

    def tangent(self, F: Tensor) -> Tensor:
        """A_ijkl = ∂P_ij/∂F_kl [Pa] (…, d, d, d, d), exact: one forward-mode derivative of :meth:`first_piola`
        per direction E_kl (d² batched calls)."""
        d = F.shape[-1]
        columns = []
        for k in range(d):
            for l in range(d):
                direction = torch.zeros_like(F)
                direction[..., k, l] = 1.0
                columns.append(torch.func.jvp(self.first_piola, (F,), (direction,))[1])
        return torch.stack(columns, -1).reshape(*F.shape, d, d)

    def params(self) -> dict[str, Any]:
        return {"material": self.name, "lam": self.lam, "mu": self.mu}


class StVenantKirchhoff(HyperelasticMaterial):
    """W = μ E:E + ½ λ (tr E)², E = ½(FᵀF − I); P = F (λ tr E I + 2 μ E). Softens without bound under
    compression (W → 0 as F → 0): fine for bending, not for crushing."""

    name = "svk"

    def _green(self, F: Tensor) -> Tensor:
        return 0.5 * (F.transpose(-1, -2) @ F - _eye(F))

    def energy_density(self, F: Tensor) -> Tensor:
        E = self._green(F)
        trace = E.diagonal(dim1=-2, dim2=-1).sum(-1)
        return self.mu * (E * E).sum((-1, -2)) + 0.5 * self.lam * trace**2

    def first_piola(self, F: Tensor) -> Tensor:
        E = self._green(F)
        trace = E.diagonal(dim1=-2, dim2=-1).sum(-1)
        return F @ (2 * self.mu * E + self.lam * trace[..., None, None] * _eye(F))


class NeoHookean(HyperelasticMaterial):
    """Compressible Neo-Hookean: W = ½ μ (tr FᵀF − d) − μ ℓ(J) + ½ λ ℓ(J)², J = det F, ℓ = ln;
    P = μ F + (λ ℓ(J) − μ) ℓ'(J) cof F (cof F = J F⁻ᵀ).

    W → ∞ as J → 0. Below J = `min_jacobian` ℓ continues as the second-order Taylor polynomial of ln about it
    (C², finite for any F), so that the pulled-back energy of an untrained field, which may invert the body at
    some points, is large and finite instead of NaN; the finite-element reference stops at such a point
    (:attr:`min_jacobian`), so it never uses the continuation."""

    name = "neo_hookean"
    needs_positive_jacobian = True

    def __init__(self, lam: float, mu: float, min_jacobian: float = 0.1) -> None:
        super().__init__(lam, mu)
        if not 0 < min_jacobian < 1:
            raise ValueError(f"NeoHookean: min_jacobian must be in (0, 1), got {min_jacobian!r}")
        self.min_jacobian = float(min_jacobian)

    def _log(self, J: Tensor) -> tuple[Tensor, Tensor]:
        """(ℓ(J), ℓ'(J)): ln J and 1/J above min_jacobian, their Taylor continuation below."""
        j = self.min_jacobian
        below = J < j
        x = J - j
        log = torch.where(below, math.log(j) + x / j - 0.5 * (x / j) ** 2, torch.log(J.clamp_min(j)))
        slope = torch.where(below, 1.0 / j - x / j**2, 1.0 / J.clamp_min(j))
        return log, slope

    def energy_density(self, F: Tensor) -> Tensor:
        d = F.shape[-1]
        log_j, _ = self._log(determinant(F))
        return 0.5 * self.mu * ((F * F).sum((-1, -2)) - d) - self.mu * log_j + 0.5 * self.lam * log_j**2

    def first_piola(self, F: Tensor) -> Tensor:
        log_j, slope = self._log(determinant(F))
        return self.mu * F + ((self.lam * log_j - self.mu) * slope)[..., None, None] * cofactor(F)


MATERIALS: dict[str, type[HyperelasticMaterial]] = {m.name: m for m in (StVenantKirchhoff, NeoHookean)}


def get_material(name: str, young: float, poisson: float) -> HyperelasticMaterial:
    """A material by name (``svk`` or ``neo_hookean``) from E [Pa] and ν."""
    if name not in MATERIALS:
        raise ValueError(f"scene.material must be one of {sorted(MATERIALS)}, got {name!r}")
    return MATERIALS[name].from_young_poisson(young, poisson)
