"""The optional potential-energy loss ℓ^E = huber((Ṽ(q̃) − V)/E_scale) of LagrangianNeuralField.losses."""
import pytest
import torch

from lnf.model import LagrangianNeuralField
from lnf.quadrature import GaussLegendre
from lnf.scenes.elastic import ElasticCantilever


@pytest.fixture
def model():
    torch.manual_seed(0)
    scene = ElasticCantilever(mesh=(4, 2))
    return LagrangianNeuralField(scene, latent_dim=1, width=16, hyper_width=8, w0=3.0, energy_weight=0.5,
                                 clamp=True, quadrature=GaussLegendre([4, 3]))


def _assert_term_is_added_and_trains(model, out, key, weighted, points, values):
    """The loss with the optional term `key` is the loss without it plus `weighted`; it reaches every parameter."""
    without = model.losses(points, values)
    assert key not in without
    torch.testing.assert_close(out["loss"], without["loss"] + weighted)
    out["loss"].backward()
    assert all(p.grad is not None for p in model.field.parameters())


def test_energy_loss_is_the_scaled_squared_potential_gap_and_trains_the_field(model):
    points = torch.rand(2, 20, 2) * torch.tensor([1.0, 0.4])
    values = 0.01 * torch.randn(2, 20, 2)
    target = torch.tensor([0.003, -0.002])
    out = model.losses(points, values, potential=target)
    codes = out["codes"]
    reduced = model.lagrangian_dynamics().potential_energy(codes)
    gap = (reduced - target) / model.scene.energy_scale
    expected = torch.where(gap.abs() < 0.1, 0.5 * gap**2, 0.1 * (gap.abs() - 0.05)).mean()
    torch.testing.assert_close(out["energy"], expected)
    _assert_term_is_added_and_trains(model, out, "energy", 0.5 * expected, points, values)


def test_negative_energy_weight_is_named():
    with pytest.raises(ValueError, match="model.energy_weight"):
        LagrangianNeuralField(ElasticCantilever(mesh=(4, 2)), width=8, hyper_width=8, energy_weight=-1.0)


def test_energy_warmup_switches_the_loss_on_then_ramps_it():
    from lnf.training.module import LNFModule

    module = LNFModule(scene={"_target_": "lnf.scenes.ElasticCantilever", "mesh": [4, 2]},
                       model={"width": 8, "hyper_width": 8, "energy_weight": 0.1},
                       quadrature={"_target_": "lnf.quadrature.GaussLegendre", "order": [4, 3]},
                       optimizer={"energy_warmup_epochs": 4})
    factors = [module.energy_factor(epoch) for epoch in range(10)]
    assert factors == [0.0, 0.0, 0.0, 0.0, 0.25, 0.5, 0.75, 1.0, 1.0, 1.0]


def test_gradient_loss_fits_the_field_gradient(model):
    """ℓ^G = (1/N) Σ ω0 ‖∇_X φ − ∇_X q‖², added with weight λ_G; it trains the field."""
    model.gradient_weight = 2.0
    points = torch.rand(2, 20, 2) * torch.tensor([1.0, 0.4])
    values = 0.01 * torch.randn(2, 20, 2)
    target = 0.05 * torch.randn(2, 20, 2, 2)
    out = model.losses(points, values, gradients=target)
    G = model.field.jet(out["codes"], points, order=1, spatial=True).G
    density = model.scene.density(points)
    expected = (density * (G - target).pow(2).sum((-1, -2))).mean(-1).mean()
    torch.testing.assert_close(out["gradient"], expected)
    _assert_term_is_added_and_trains(model, out, "gradient", 2.0 * expected, points, values)
    with pytest.raises(ValueError, match="gradient_weight"):
        LagrangianNeuralField(model.scene, gradient_weight=-1.0)
