"""The optional dynamics-residual loss ℓ^D of LagrangianNeuralField.losses: the pulled-back equations' acceleration
against the code acceleration of the observed motion."""
import pytest
import torch

from lnf.model import LagrangianNeuralField
from lnf.quadrature import GaussLegendre
from lnf.scenes import LiftedPendulum


@pytest.fixture
def model():
    torch.manual_seed(0)
    return LagrangianNeuralField(LiftedPendulum(), latent_dim=2, width=16, hyper_width=8, w0=3.0,
                                 dynamics_weight=0.5, quadrature=GaussLegendre(6)).double()


def _motion_on_the_manifold(model, codes, code_velocity, code_acceleration, points):
    """u̇ = J q̃̇ and ü = J q̃̈ + H[q̃̇, q̃̇] of a motion through φ at `points` (B, N, dim_B)."""
    jet = model.field.jet(codes, points, order=2)
    velocities = torch.einsum("bnai,bi->bna", jet.J, code_velocity)
    accelerations = torch.einsum("bnai,bi->bna", jet.J, code_acceleration) \
        + torch.einsum("bnaij,bi,bj->bna", jet.H, code_velocity, code_velocity)
    return velocities, accelerations


def test_the_residual_vanishes_for_motion_that_obeys_the_pulled_back_equations(model):
    """On φ's manifold, with ü from the model's own acceleration, ℓ^D is zero to rounding; a motion with another
    acceleration gives the Huber loss of the stated relative gap."""
    torch.manual_seed(1)
    codes = 0.3 * torch.randn(3, 2, dtype=torch.float64)
    code_velocity = 0.5 * torch.randn(3, 2, dtype=torch.float64)
    points = torch.rand(3, 40, 2, dtype=torch.float64) * 2 - 1
    weights = torch.full((3, 40), 4.0 / 40, dtype=torch.float64) * model._density(points)
    with torch.no_grad():
        true = model.lagrangian_dynamics().acceleration(codes, code_velocity)
        velocities, accelerations = _motion_on_the_manifold(model, codes, code_velocity, true, points)
        valid = torch.tensor([True, True, False])
        zero = model._dynamics_residual(codes, points, weights, velocities, accelerations, valid)
        assert zero[:2].abs().max() < 1e-8 and zero[2] == 0
        other = true + torch.tensor([[1.0, 0.0], [0.0, -2.0], [0.0, 0.0]], dtype=torch.float64)
        velocities, accelerations = _motion_on_the_manifold(model, codes, code_velocity, other, points)
        residual = model._dynamics_residual(codes, points, weights, velocities, accelerations, valid)
    gap = torch.tensor([1.0, 2.0], dtype=torch.float64) / other[:2].pow(2).sum(-1).mean().sqrt()
    huber = torch.where(gap < 1, 0.5 * gap ** 2, gap - 0.5)
    torch.testing.assert_close(residual, torch.cat([huber, torch.zeros(1, dtype=huber.dtype)]))


def test_the_loss_adds_the_weighted_term_and_trains_the_field(model):
    points = torch.rand(2, 30, 2, dtype=torch.float64) * 2 - 1
    values = 0.1 * torch.randn(2, 30, 1, dtype=torch.float64)
    velocities, accelerations = torch.randn_like(values), torch.randn_like(values)
    out = model.losses(points, values, velocities, accelerations=accelerations,
                       acceleration_valid=torch.tensor([True, False]))
    without = model.losses(points, values, velocities)
    assert "dynamics" in out and "dynamics" not in without
    torch.testing.assert_close(out["loss"], without["loss"] + 0.5 * out["dynamics"] / 2)
    off = model.losses(points, values, velocities, energy_factor=0.0, accelerations=accelerations,
                       acceleration_valid=torch.tensor([True, False]))
    assert "dynamics" not in off  # the schedule of the energy loss: off during its warm-up
    out["loss"].backward()
    assert all(p.grad is not None for p in model.field.parameters())


def test_forced_scenes_and_negative_weights_are_refused():
    from lnf.scenes.elastic import ElasticCantilever

    with pytest.raises(ValueError, match="model.dynamics_weight must be a finite number ≥ 0"):
        LagrangianNeuralField(LiftedPendulum(), width=8, hyper_width=8, dynamics_weight=-1.0)
    forced = ElasticCantilever(mesh=(4, 2), damping=0.5)
    with pytest.raises(ValueError, match="non-conservative forces; set model.dynamics_weight=0"):
        LagrangianNeuralField(forced, width=8, hyper_width=8, dynamics_weight=1.0)
