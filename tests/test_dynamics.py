"""Reduced dynamics against closed forms (docs/method.md §5, §7.1)."""
import numpy as np
import torch

from analytic import LinearModeEmbedding, NonlinearEmbedding
from lnf.dynamics import ReducedDynamics
from lnf.integrators import get_integrator
from lnf.quadrature import Quadrature, gauss_legendre_rule
from lnf.scenes.base import DiscretePotential, Scene


def _pendulum_dynamics(scene, order=8):
    quad = gauss_legendre_rule(order, scene.bounds).to(torch.float64)
    return ReducedDynamics(LinearModeEmbedding(scene).jet, scene, quad)


def test_linear_mode_gives_the_pendulum(pendulum):
    dyn = _pendulum_dynamics(pendulum)
    q = torch.tensor([[-1.3], [0.0], [0.4], [2.5]], dtype=torch.float64)
    v = torch.tensor([[0.3], [-1.0], [2.0], [0.1]], dtype=torch.float64)
    terms = dyn.terms(q, v)
    mgl = pendulum.mass * pendulum.gravity * pendulum.length
    torch.testing.assert_close(terms.mass[:, 0, 0], torch.full((4,), pendulum.inertia, dtype=torch.float64))
    torch.testing.assert_close(terms.coriolis, torch.zeros_like(q))
    torch.testing.assert_close(terms.gravity, mgl * torch.sin(q))
    torch.testing.assert_close(terms.potential, mgl * (1 - torch.cos(q[:, 0])))
    T, V = dyn.energies(q, v)
    torch.testing.assert_close(T, 0.5 * pendulum.inertia * v[:, 0] ** 2)


def test_linear_mode_rollout_matches_ode(pendulum):
    dyn = _pendulum_dynamics(pendulum)
    states0 = np.array([[1.2, 0.5], [-0.4, -1.0], [0.1, 0.9]])
    times = 0.05 * np.arange(101)
    ref = pendulum.simulate(states0, times)
    q0 = torch.tensor(states0[:, :1]); v0 = torch.tensor(states0[:, 1:])
    for name, tol in [("rk4", 2e-4), ("dopri5", 1e-6), ({"name": "implicit_midpoint", "order": 4}, 1e-3)]:
        traj = get_integrator(name).integrate(dyn, q0, v0, 0.05, 100)
        assert np.abs(traj.q[..., 0].numpy() - ref[..., 0]).max() < tol, name
        assert np.abs(traj.v[..., 0].numpy() - ref[..., 1]).max() < 10 * tol, name


class _QuadraticPotential(DiscretePotential):
    def __init__(self, weights):
        self.weights = weights

    def __call__(self, q, G=None):
        return 0.5 * torch.einsum("bn,n->b", q[..., 0] ** 2, self.weights) + torch.einsum("bn,n->b", q[..., 0], self.weights) ** 3


class _ToyScene(Scene):
    name, field_dim = "toy", 1
    bounds = [[0.0, 1.0]]
    energy_scale = 1.0

    def __init__(self, density):
        self._density = density

    def density(self, points):
        return self._density.to(points.dtype)

    def potential(self, quadrature):
        return _QuadraticPotential(quadrature.weights)

    def params(self):
        return {}


def _nonlinear_setup(n=11):
    emb = NonlinearEmbedding(n)
    g = torch.Generator().manual_seed(3)
    points = torch.rand(n, 1, generator=g, dtype=torch.float64)
    weights = torch.rand(n, generator=g, dtype=torch.float64)
    density = 0.5 + torch.rand(n, generator=g, dtype=torch.float64)
    scene = _ToyScene(density)
    return emb, ReducedDynamics(emb.jet, scene, Quadrature(points, weights)), weights * density


def test_pullback_mass_matrix_closed_form():
    emb, dyn, ww = _nonlinear_setup()
    q = torch.tensor([[0.3, -0.7], [1.1, 0.2]], dtype=torch.float64)
    terms = dyn.terms(q, torch.zeros_like(q))
    for b in range(2):
        q1, q2 = q[b]
        df = torch.tensor([[torch.cos(q1), 0.0], [q2, q1], [0.0, 2 * q2], [0.0, -torch.sin(q2)]], dtype=torch.float64)
        J = emb.a @ df  # (N, 2)
        M = torch.einsum("n,ni,nj->ij", ww, J, J)
        torch.testing.assert_close(terms.mass[b], M)
        assert torch.linalg.eigvalsh(M).min() > 0


def test_coriolis_equals_christoffel_form():
    """c̃_i = Σ_jk Γ_ijk q̇_j q̇_k with Γ_ijk = ½(∂_k M_ij + ∂_j M_ik − ∂_i M_jk) (autograd of M̃)."""
    emb, dyn, _ = _nonlinear_setup()
    q = torch.tensor([[0.3, -0.7], [1.1, 0.2]], dtype=torch.float64)
    v = torch.tensor([[0.5, 1.5], [-2.0, 0.7]], dtype=torch.float64)
    c = dyn.terms(q, v).coriolis
    for b in range(2):
        dM = torch.autograd.functional.jacobian(lambda x: dyn.mass_matrix(x[None])[0], q[b])  # (i, j, k)
        gamma = 0.5 * (dM + dM.permute(0, 2, 1) - dM.permute(2, 0, 1))
        torch.testing.assert_close(c[b], torch.einsum("ijk,j,k->i", gamma, v[b], v[b]))


def test_gravity_is_gradient_of_pulled_back_potential():
    emb, dyn, _ = _nonlinear_setup()
    q = torch.tensor([[0.3, -0.7]], dtype=torch.float64)
    g = dyn.terms(q, torch.zeros_like(q)).gravity
    ref = torch.autograd.functional.jacobian(lambda x: dyn.potential_energy(x[None])[0], q[0])
    torch.testing.assert_close(g[0], ref)


def test_energy_conserved_by_nonlinear_system():
    _, dyn, _ = _nonlinear_setup()
    q0 = torch.tensor([[0.3, -0.7]], dtype=torch.float64)
    v0 = torch.tensor([[0.2, 0.1]], dtype=torch.float64)
    traj = get_integrator("dopri5").integrate(dyn, q0, v0, 0.01, 200)
    T, V = dyn.energies(traj.q, traj.v)
    E = T + V
    assert (E - E[:, :1]).abs().max() < 1e-6


def test_field_gradient_potential_uses_mixed_derivatives():
    """V = ½ Σ w ‖∇_X q‖²: g̃ from the jet's GJ equals autograd of the pulled-back V."""
    from lnf.siren import ModulatedSiren

    class GradientEnergy(DiscretePotential):
        needs_gradient = True

        def __init__(self, w):
            self.w = w

        def __call__(self, q, G=None):
            return 0.5 * torch.einsum("bnak,n->b", G**2, self.w)

    class Elastic(_ToyScene):
        bounds = [[-1.0, 1.0], [-1.0, 1.0]]

        def potential(self, quadrature):
            return GradientEnergy(quadrature.weights)

    torch.manual_seed(0)
    field = ModulatedSiren(latent_dim=2, out_dim=2, width=16, hyper_init_scale=1.0).double()
    quad = gauss_legendre_rule(3, Elastic.bounds).to(torch.float64)
    dyn = ReducedDynamics(field.jet, Elastic(torch.ones(9, dtype=torch.float64)), quad)
    q = torch.tensor([[0.2, -0.4]], dtype=torch.float64)
    g = dyn.terms(q, torch.zeros_like(q)).gravity
    ref = torch.autograd.functional.jacobian(lambda x: dyn.potential_energy(x[None])[0], q[0])
    torch.testing.assert_close(g[0], ref)


def test_static_terms_are_those_of_the_full_terms():
    """M̃, Ṽ, g̃ from the first-order jet equal those of terms() (which also computes H and the velocity terms)."""
    _, dyn, _ = _nonlinear_setup()
    q = torch.tensor([[0.3, -0.7], [1.1, 0.2]], dtype=torch.float64)
    terms = dyn.terms(q, torch.ones_like(q))
    for a, b in zip(dyn.static_terms(q), (terms.mass, terms.potential, terms.gravity)):
        torch.testing.assert_close(a, b)
