"""The reduction ρ̃: K unrolled gradient steps on the reconstruction loss (docs/method.md §3).

Shapes: codes q̃ (B, d); points (N, dim_B) or (B, N, dim_B); values (B, N, A); density ω0 (N,) or (B, N);
quadrature weights (N,) or (B, N).
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from lnf.siren import FieldJet, ModulatedSiren


def reconstruction_loss(pred: Tensor, target: Tensor, density: Tensor) -> Tensor:
    """ℓ^r = (1/|X|) Σ_j ω0(X_j) ‖pred_j − target_j‖², per batch element (B,)."""
    return (density * (pred - target).pow(2).sum(-1)).mean(-1)


def reduce(
    field: ModulatedSiren,
    points: Tensor,
    values: Tensor,
    density: Tensor,
    step_size: Tensor,
    steps: int,
    codes: Optional[Tensor] = None,
    first_jet: Optional[FieldJet] = None,
) -> Tensor:
    """q̃^K from q̃^0 = 0 (or `codes`) by q̃ ← q̃ − α ∇_q̃ ℓ^r(values, φ(q̃)).

    The gradient ∇_q̃ ℓ^r = (2/|X|) Σ_j ω0 J_jᵀ (φ_j − q_j) comes from the forward-mode jet, so the
    result is an ordinary differentiable function of the parameters: backpropagating through it is the
    exact second-order gradient of the unrolled steps (what `create_graph=True` would give).

    `first_jet`: the order-1 jet of φ at q̃^0 and these points, if the caller has it (it does not depend on
    `values`: two reductions from the same start, such as ρ̃(q) and ρ̃(φ(ρ̃(q))) in training, share it).
    """
    if steps < 1:
        raise ValueError(f"reduction steps K must be ≥ 1, got {steps}")
    B = values.shape[0]
    if codes is None:
        codes = values.new_zeros(B, field.latent_dim)
    n = values.shape[-2]
    for k in range(steps):
        jet = first_jet if k == 0 and first_jet is not None else field.jet(codes, points, order=1)
        residual = density[..., None] * (jet.value - values)  # (B, N, A)
        grad = (2.0 / n) * torch.einsum("bna,bnad->bd", residual, jet.J)
        codes = codes - step_size * grad
    return codes


def start_grid(latent_dim: int, per_axis: int, radius: float) -> Tensor:
    """Candidate initial codes: a tensor grid of `per_axis` points per axis on [−radius, radius]^d,
    (per_axis^d, d); a single point is the origin (the paper's q̃^0 = 0)."""
    if per_axis == 1:
        return torch.zeros(1, latent_dim)
    axis = torch.linspace(-radius, radius, per_axis)
    return torch.cartesian_prod(*[axis] * latent_dim).reshape(-1, latent_dim)


def best_start(field: ModulatedSiren, points: Tensor, values: Tensor, density: Tensor, starts: Tensor) -> Tensor:
    """Per batch element, the candidate of `starts` (S, d) with the smallest ℓ^r: (B, d).

    A coarse search before the gradient steps, for fields whose gradient from q̃ = 0 carries no information
    (a bump far from where φ(0) puts it); the choice is a constant of the graph (no gradient flows through it).
    """
    B, S = values.shape[0], starts.shape[0]
    starts = starts.to(values)
    with torch.no_grad():
        codes = starts.repeat(B, 1)  # row b·S + s is start s for element b
        pts = points if points.ndim == 2 else points.repeat_interleave(S, 0)
        dens = density if density.ndim == 1 else density.repeat_interleave(S, 0)
        loss = reconstruction_loss(field(codes, pts), values.repeat_interleave(S, 0), dens)
        return starts[loss.view(B, S).argmin(1)]


def pullback_mass_matrix(J: Tensor, weights: Tensor) -> Tensor:
    """M̃ = Σ_j w_j ω0_j J_jᵀ J_j (B, d, d); `weights` already include ω0: (N,) or (B, N)."""
    return torch.einsum("bn,bnai,bnaj->bij", weights.expand(J.shape[:2]), J, J)


def project_velocity(J: Tensor, weights: Tensor, velocities: Tensor) -> Tensor:
    """q̃̇ = argmin_v ‖J v − q̇‖²_ω0 = M̃⁻¹ Σ_j w_j ω0_j J_jᵀ q̇_j (B, d); weights include ω0."""
    M = pullback_mass_matrix(J, weights)
    rhs = torch.einsum("bn,bnai,bna->bi", weights.expand(J.shape[:2]), J, velocities)
    return solve_mass(M, rhs)


def solve_mass(mass: Tensor, rhs: Tensor) -> Tensor:
    """M̃⁻¹ rhs (B, d); rows whose M̃ is singular (φ not an immersion there) come back as NaN, so that
    rollouts report them as diverged instead of failing inside torch."""
    x, info = torch.linalg.solve_ex(mass, rhs)
    return torch.where((info == 0)[:, None], x, torch.full_like(x, float("nan")))


def projection_loss(codes: Tensor, reprojected: Tensor, mass: Tensor) -> Tensor:
    """ℓ^p = (q̃ − q̃')ᵀ M̃(q̃) (q̃ − q̃') per batch element (B,)."""
    diff = codes - reprojected
    return torch.einsum("bi,bij,bj->b", diff, mass, diff)
