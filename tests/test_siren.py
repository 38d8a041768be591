import pytest
import torch
from torch.func import jacfwd, vmap

from lnf.siren import ModulatedSiren


def _reference(m, q, X):
    f = lambda qq, xx: m(qq[None], xx[None])[0, 0]  # noqa: E731  (A,)
    J = vmap(vmap(jacfwd(f, 0), (None, 0)), (0, None))(q, X)
    H = vmap(vmap(jacfwd(jacfwd(f, 0), 0), (None, 0)), (0, None))(q, X)
    G = vmap(vmap(jacfwd(f, 1), (None, 0)), (0, None))(q, X)
    GJ = vmap(vmap(jacfwd(jacfwd(f, 1), 0), (None, 0)), (0, None))(q, X)
    return J, H, G, GJ


@pytest.mark.parametrize("latent_dim,hyper_depth,depth,out_dim", [(1, 0, 2, 1), (2, 1, 3, 2), (3, 2, 1, 1)])
def test_jet_matches_autodiff(latent_dim, hyper_depth, depth, out_dim):
    torch.manual_seed(0)
    m = ModulatedSiren(latent_dim=latent_dim, hyper_depth=hyper_depth, depth=depth, width=24, out_dim=out_dim,
                       hyper_width=16, hyper_init_scale=1.0).double()
    q = torch.randn(3, latent_dim, dtype=torch.float64)
    X = torch.rand(7, 2, dtype=torch.float64) * 2 - 1
    J, H, G, GJ = _reference(m, q, X)
    jet = m.jet(q, X, order=2, spatial=True)
    torch.testing.assert_close(jet.value, m(q, X))
    for name, ref in [("J", J), ("H", H), ("G", G), ("GJ", GJ)]:
        torch.testing.assert_close(getattr(jet, name), ref, rtol=1e-10, atol=1e-10, msg=name)
    # lower orders return the same numbers and nothing more
    j1 = m.jet(q, X, order=1)
    torch.testing.assert_close(j1.J, J)
    assert j1.H is None and j1.G is None
    # per-batch points give the same as shared points
    torch.testing.assert_close(m.jet(q, X.expand(3, 7, 2), order=2).H, H)


def test_jet_against_finite_differences():
    torch.manual_seed(1)
    m = ModulatedSiren(latent_dim=2, hyper_depth=1, width=32, w0=30.0, hyper_init_scale=1.0).double()
    q = torch.randn(2, 2, dtype=torch.float64) * 0.3
    X = torch.rand(5, 2, dtype=torch.float64) * 2 - 1
    jet = m.jet(q, X, order=2, spatial=True)
    h = 1e-6
    for i in range(2):
        e = torch.zeros(2, dtype=torch.float64)
        e[i] = h
        fd = (m(q + e, X) - m(q - e, X)) / (2 * h)
        torch.testing.assert_close(jet.J[..., i], fd, rtol=1e-5, atol=1e-6)
        fd2 = (m.jet(q + e, X, order=1).J - m.jet(q - e, X, order=1).J) / (2 * h)
        torch.testing.assert_close(jet.H[..., i, :], fd2, rtol=1e-5, atol=1e-5)
        fdx = (m(q, X + e) - m(q, X - e)) / (2 * h)
        torch.testing.assert_close(jet.G[..., i], fdx, rtol=1e-5, atol=1e-5)


def test_backprop_through_jet_matches_double_backward():
    """Gradients of a J-dependent loss through the jet equal create_graph=True double backward."""
    torch.manual_seed(2)
    m = ModulatedSiren(latent_dim=1, width=16).double()
    q = torch.randn(4, 1, dtype=torch.float64, requires_grad=True)
    X = torch.rand(6, 2, dtype=torch.float64)
    loss_jet = m.jet(q, X, order=1).J.pow(2).sum()
    params = list(m.parameters())
    g_jet = torch.autograd.grad(loss_jet, params, allow_unused=True)
    out = m(q, X)
    loss_ref = sum(torch.autograd.grad(out[:, n].sum(), q, create_graph=True)[0].pow(2).sum() for n in range(6))
    g_ref = torch.autograd.grad(loss_ref, params, allow_unused=True)
    for p, a, b in zip(params, g_jet, g_ref):
        a = torch.zeros_like(p) if a is None else a
        b = torch.zeros_like(p) if b is None else b
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize("kwargs,match", [({"latent_dim": 0}, "latent_dim"), ({"depth": 0}, "depth"),
                                          ({"width": 0}, "width"), ({"w0": 0.0}, "w0")])
def test_bad_hyperparameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ModulatedSiren(**kwargs)


def test_bad_shapes():
    m = ModulatedSiren(latent_dim=2, width=8)
    with pytest.raises(ValueError, match="codes"):
        m(torch.zeros(3, 1), torch.zeros(4, 2))
    with pytest.raises(ValueError, match="points"):
        m(torch.zeros(3, 2), torch.zeros(0, 2))


def test_sin_cos_function_has_exact_gradients_jvp_and_double_backward():
    """The jet's fused (sin, cos) passes torch's gradient, forward-mode and second-order checks."""
    from lnf.siren import _SinCos

    x = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: _SinCos.apply(t), (x,))
    assert torch.autograd.gradgradcheck(lambda t: _SinCos.apply(t), (x,))
    tangent = torch.randn_like(x)
    (s, c), (ds, dc) = torch.func.jvp(lambda t: _SinCos.apply(t), (x.detach(),), (tangent,))
    torch.testing.assert_close(ds, torch.cos(x.detach()) * tangent)
    torch.testing.assert_close(dc, -torch.sin(x.detach()) * tangent)


def test_values_only_decoding_under_no_grad_equals_the_autograd_path():
    """The in-place values path (no autograd, no torch.func transform) gives the recorded path's numbers."""
    torch.manual_seed(1)
    m = ModulatedSiren(latent_dim=2, depth=3, width=32, hyper_depth=1, hyper_width=16)
    q, X = torch.randn(4, 2), torch.rand(9, 2) * 2 - 1
    recorded = m(q, X)
    assert recorded.requires_grad
    with torch.no_grad():
        torch.testing.assert_close(m(q, X), recorded.detach())  # float32 rounding of another summation order
