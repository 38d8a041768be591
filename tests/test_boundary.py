"""The clamped field φ = s ψ: zero on the clamp, and its jet is the product rule of the SIREN's."""
import torch
from torch.func import jacfwd

from lnf.boundary import ClampedField
from lnf.scenes.elastic import ElasticCantilever
from lnf.siren import ModulatedSiren


def test_clamped_field_is_zero_on_the_clamp_and_its_jet_matches_autodiff():
    torch.manual_seed(0)
    scene = ElasticCantilever(mesh=(4, 2))
    siren = ModulatedSiren(latent_dim=2, in_dim=2, out_dim=2, width=16, depth=2, w0=3.0, hyper_width=8).double()
    field = ClampedField(siren, scene.clamp_factor)
    assert (field.latent_dim, field.depth) == (2, 2)  # what the roofline study reads of the field
    codes = torch.randn(3, 2, dtype=torch.float64)
    points = torch.rand(5, 2, dtype=torch.float64) * torch.tensor([1.0, 0.4], dtype=torch.float64)
    clamp = points.clone()
    clamp[:, 0] = 0.0
    assert field(codes, clamp).abs().max() == 0.0
    jet = field.jet(codes, points, order=2, spatial=True)
    torch.testing.assert_close(jet.value, field(codes, points))

    def phi(q, x):  # one code (d,), one point (2,) -> (A,)
        return field(q[None], x[None])[0, 0]

    for b in range(3):
        for n in range(5):
            q, x = codes[b], points[n]
            torch.testing.assert_close(jet.J[b, n], jacfwd(phi, 0)(q, x))
            torch.testing.assert_close(jet.H[b, n], jacfwd(jacfwd(phi, 0), 0)(q, x))
            torch.testing.assert_close(jet.G[b, n], jacfwd(phi, 1)(q, x))
            torch.testing.assert_close(jet.GJ[b, n], jacfwd(jacfwd(phi, 1), 0)(q, x))


def test_clamp_on_a_scene_without_one_is_a_clear_error():
    import pytest

    from lnf.model import LagrangianNeuralField
    from lnf.scenes.pendulum import LiftedPendulum

    with pytest.raises(ValueError, match="model.clamp=false"):
        LagrangianNeuralField(LiftedPendulum(), width=8, hyper_width=8, clamp=True)
