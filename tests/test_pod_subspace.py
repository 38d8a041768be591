"""φ = m + Φ q̃ + ψ (model.pod_subspace): the jet is the sum's, training starts at POD-Galerkin, ρ̃ starts at the
projection onto the modes."""
import copy

import numpy as np
import torch

from lnf.baselines.pod import LinearEmbedding, PODGalerkin
from lnf.model import LagrangianNeuralField
from lnf.closure import CODE_SPAN_FLOOR
from lnf.pod_subspace import SubspacePlusField
from lnf.scenes.elastic import ElasticCantilever
from lnf.siren import ModulatedSiren


def _observations(scene, n=4, T=6, N=40, seed=0):
    """Fields of two smooth shapes with random amplitudes at random points: (n, N, 2), (n, T, N, 2)."""
    rng = np.random.default_rng(seed)
    points = rng.uniform([0, 0], [1.0, 0.4], size=(n, N, 2))
    shapes = np.stack([points[..., 0] ** 2, points[..., 0] * points[..., 1]], -1)  # (n, N, 2)
    amps = rng.normal(size=(n, T, 2))
    values = amps[..., 0, None, None] * shapes[:, None] + amps[..., 1, None, None] * shapes[:, None, :, ::-1] ** 2
    return points, values


def test_the_jet_is_the_sum_of_the_subspace_and_the_siren_and_matches_autodiff():
    torch.manual_seed(0)
    scene = ElasticCantilever(mesh=(4, 2))
    linear = LinearEmbedding(scene.bounds, 2, 2, degree=3).double()
    linear.set_subspace(torch.randn(16, 2, dtype=torch.float64), torch.randn(16, 2, 2, dtype=torch.float64))
    siren = ModulatedSiren(latent_dim=2, in_dim=2, out_dim=2, width=16, depth=2, w0=3.0, hyper_width=8).double()
    field = SubspacePlusField(linear, siren, residual_scale=0.3)  # φ = m + Φ q̃ + 0.3 ψ
    codes = torch.randn(3, 2, dtype=torch.float64)
    points = torch.rand(5, 2, dtype=torch.float64) * torch.tensor([1.0, 0.4], dtype=torch.float64)
    jet = field.jet(codes, points, order=2, spatial=True)
    torch.testing.assert_close(jet.value, linear(codes, points) + 0.3 * siren(codes, points))
    torch.testing.assert_close(field(codes, points), jet.value)

    a, b = linear.jet(codes, points, order=1, spatial=True), siren.jet(codes, points, order=2, spatial=True)
    torch.testing.assert_close(jet.G, a.G + 0.3 * b.G)  # the parts' own jets are checked against autodiff elsewhere
    torch.testing.assert_close(jet.GJ, a.GJ + 0.3 * b.GJ)
    eps = 1e-6  # (the Legendre basis is evaluated in NumPy, outside autodiff: central differences in q̃)
    for i in range(2):
        step = torch.zeros(2, dtype=torch.float64)
        step[i] = eps
        plus, minus = field.jet(codes + step, points, order=1), field.jet(codes - step, points, order=1)
        torch.testing.assert_close(jet.J[..., i], (plus.value - minus.value) / (2 * eps), atol=1e-6, rtol=1e-6)
        torch.testing.assert_close(jet.H[..., i], (plus.J - minus.J) / (2 * eps), atol=1e-6, rtol=1e-6)


def test_an_untrained_model_is_pod_galerkin_and_reduces_to_the_projection():
    torch.manual_seed(0)
    scene = ElasticCantilever(mesh=(4, 2))
    points, values = _observations(scene)
    model = LagrangianNeuralField(scene, latent_dim=2, width=16, hyper_width=8, w0=3.0, pod_subspace=True,
                                  pod_degree=4).double()
    assert model.needs_fit
    model.fit_subspace(points, values)
    assert not model.needs_fit
    pod = PODGalerkin(scene, latent_dim=2, degree=4).double()
    pod.fit_to_observations(points, values)
    x = torch.as_tensor(points[0])
    q = torch.as_tensor(values[0])  # (T, N, 2)
    ours, theirs = model.reduce(x, q), pod.reduce(x, q)
    # the same subspace, every mode scaled by the first one's spread: the same fields, from codes rescaled
    torch.testing.assert_close(model.decode(ours, x), pod.decode(theirs, x))
    torch.testing.assert_close(model.decode(ours, x), q, atol=1e-8, rtol=1e-8)  # two shapes, two modes: exact
    # the first code has unit variance on the training snapshots, the second that of its mode relative to the first
    codes = torch.cat([model.reduce(torch.as_tensor(points[i]), torch.as_tensor(values[i])) for i in range(4)])
    ratio = float(pod.singular_values[1] / pod.singular_values[0])
    torch.testing.assert_close(codes.std(0), torch.tensor([1.0, ratio], dtype=torch.float64), rtol=0.2, atol=0.0)
    # so the codes share one unit: a barely moving code is measured by a floor of the largest span (POD-Galerkin's too);
    # a plain SIREN's codes are each their own
    assert model.code_span_floor == pod.code_span_floor == CODE_SPAN_FLOOR > 0
    plain = LagrangianNeuralField(scene, latent_dim=2, width=16, hyper_width=8, w0=3.0)
    assert plain.code_span_floor == 0.0
    # and the linear part's pulled-back mass is a multiple of the identity (modes of equal L² norm, orthogonal)
    modes = model.field.linear.modes.flatten(0, 1)
    gram = modes.T @ modes
    torch.testing.assert_close(gram, gram[0, 0] * torch.eye(2, dtype=torch.float64))


def test_the_subspace_jet_runs_under_torch_func_with_points_wrapped_by_it():
    """The tabulated pullback differentiates M̃ with torch.func.jvp, where ``points.to(codes)`` wraps the points:
    the Legendre basis (evaluated in NumPy) is read from the points themselves, and the derivative is Φ·tangent
    (it failed with 'Cannot access data pointer of Tensor that doesn't have storage')."""
    torch.manual_seed(0)
    scene = ElasticCantilever(mesh=(4, 2))
    linear = LinearEmbedding(scene.bounds, 2, 2, degree=3).double()
    linear.set_subspace(torch.randn(16, 2, dtype=torch.float64), torch.randn(16, 2, 2, dtype=torch.float64))
    points = torch.rand(5, 2, dtype=torch.float64) * torch.tensor([1.0, 0.4], dtype=torch.float64)
    codes, tangent = torch.randn(3, 2, dtype=torch.float64), torch.randn(3, 2, dtype=torch.float64)
    _, derivative = torch.func.jvp(lambda c: linear(c, points.to(c)), (codes,), (tangent,))
    J = linear.jet(codes, points, order=1).J
    torch.testing.assert_close(derivative, torch.einsum("bnai,bi->bna", J, tangent))
    # a model copied after a table was built (experiments/scenes.py copies it for its damped rollout) copies without
    # the basis cache, whose entries may hold the transform's wrapped tensors
    torch.func.jvp(lambda c: linear(c, points.to(c)), (codes,), (tangent,))
    twin = copy.deepcopy(linear)
    assert twin._cache == {}
    torch.testing.assert_close(twin(codes, points), linear(codes, points))


def test_the_linear_embedding_evaluates_only_the_degrees_its_coefficients_use():
    """Coefficients up to degree 2 of a degree-5 basis: the jet (value, J, H, G, GJ) is the full basis's, from the
    degree-2 basis alone; new coefficients (set_subspace, load_state_dict) are seen."""
    torch.manual_seed(0)
    scene = ElasticCantilever(mesh=(4, 2))
    linear = LinearEmbedding(scene.bounds, 2, 2, degree=5).double()
    low = torch.as_tensor(linear.basis.multi_indices().max(1) <= 2)
    mean = torch.randn(36, 2, dtype=torch.float64) * low[:, None]
    modes = torch.randn(36, 2, 2, dtype=torch.float64) * low[:, None, None]
    quad = torch.randn(36, 2, 2, 2, dtype=torch.float64) * low[:, None, None, None]
    linear.set_subspace(mean, modes, quad + quad.transpose(-1, -2))
    points = torch.rand(7, 2, dtype=torch.float64) * torch.tensor([1.0, 0.4], dtype=torch.float64)
    codes = torch.randn(3, 2, dtype=torch.float64)
    jet = linear.jet(codes, points, order=2, spatial=True)
    assert linear._coefficients()[0].degree == 2
    basis = torch.as_tensor(linear.basis.values(points.numpy()))  # the full degree-5 basis (36 functions)
    grad = torch.as_tensor(linear.basis.gradients(points.numpy()))
    Hq = 2 * torch.einsum("nc,caij,zj->znai", basis, linear.quad, codes)  # c: basis function, z: batch
    J = torch.einsum("nc,cai->nai", basis, linear.modes) + Hq
    value = torch.einsum("nc,ca->na", basis, linear.mean) + torch.einsum("nc,cai,zi->zna", basis, linear.modes, codes) \
        + 0.5 * torch.einsum("znai,zi->zna", Hq, codes)
    G = torch.einsum("nck,ca->nak", grad, linear.mean) + torch.einsum("nck,cai,zi->znak", grad, linear.modes, codes) \
        + torch.einsum("nck,caij,zi,zj->znak", grad, linear.quad, codes, codes)
    torch.testing.assert_close(jet.value, value)
    torch.testing.assert_close(jet.J, J)
    torch.testing.assert_close(jet.H, 2 * torch.einsum("nc,caij->naij", basis, linear.quad).expand_as(jet.H))
    torch.testing.assert_close(jet.G, G)
    full = torch.randn(36, 2, dtype=torch.float64)  # every degree used: the whole basis again
    linear.load_state_dict({**linear.state_dict(), "mean": full})
    assert linear._coefficients()[0].degree == 5
    torch.testing.assert_close(linear(codes, points)[0], torch.einsum("nc,ca->na", basis, full)
                               + torch.einsum("nc,cai,i->na", basis, linear.modes, codes[0])
                               + torch.einsum("nc,caij,i,j->na", basis, linear.quad, codes[0], codes[0]))
