"""The mass-conditioning loss ℓ^M (LagrangianNeuralField.losses): zero at d = 1, positive on a degenerate tangent."""
import torch

from lnf.model import LagrangianNeuralField
from lnf.scenes import LiftedPendulum


def _snapshots(n=4, points=64):
    torch.manual_seed(0)
    return torch.rand(n, points, 2) * 2 - 1, torch.randn(n, points, 1)


def test_zero_at_one_latent_dimension():
    model = LagrangianNeuralField(LiftedPendulum(), latent_dim=1, width=16, hyper_width=8)
    out = model.losses(*_snapshots())
    assert "mass_condition" not in out  # d = 1: cond M̃ = 1, nothing to keep


def test_positive_and_decreasing_under_its_gradient_on_a_degenerate_tangent():
    model = LagrangianNeuralField(LiftedPendulum(), latent_dim=2, width=16, hyper_width=8, mass_condition_max=1.0)
    points, values = _snapshots()
    out = model.losses(points, values)
    assert out["mass_condition"].item() > 0  # κ = 1: any anisotropy of M̃ costs
    off = LagrangianNeuralField(LiftedPendulum(), latent_dim=2, width=16, hyper_width=8, mass_condition_weight=0.0)
    assert "mass_condition" not in off.losses(points, values)
    before = out["mass_condition"].item()
    opt = torch.optim.Adam(model.field.parameters(), lr=1e-2)
    for _ in range(30):
        opt.zero_grad()
        model.losses(points, values)["mass_condition"].backward()
        opt.step()
    assert model.losses(points, values)["mass_condition"].item() < before
