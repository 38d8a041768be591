"""The lifted double pendulum: closed-form scene against the pulled-back reduced dynamics."""
import numpy as np
import pytest
import torch

from analytic import ModeMapEmbedding
from lnf.dynamics import ReducedDynamics
from lnf.integrators import get_integrator
from lnf.quadrature import gauss_legendre_rule
from lnf.scenes.double_pendulum import LiftedDoublePendulum


@pytest.fixture
def scene():
    return LiftedDoublePendulum(masses=(1.0, 0.7), lengths=(1.0, 0.8))


def _dynamics(scene, nonlinear=False):
    quad = gauss_legendre_rule(8, scene.bounds).to(torch.float64)
    return ReducedDynamics(ModeMapEmbedding(scene.mode_values, nonlinear).jet, scene, quad)


def test_modes_are_orthonormal(scene):
    quad = gauss_legendre_rule(8, scene.bounds)
    u = scene.mode_values(quad.points.double().numpy())
    gram = np.einsum("in,jn,n->ij", u, u, quad.weights.double().numpy())
    np.testing.assert_allclose(gram, np.eye(2), atol=1e-10)


def test_mode_embedding_gives_the_double_pendulum(scene):
    dyn = _dynamics(scene)
    q = torch.tensor([[0.3, -1.1], [2.0, 0.4], [0.0, 0.0]], dtype=torch.float64)
    v = torch.tensor([[1.0, 0.5], [-0.3, 2.0], [0.7, -0.2]], dtype=torch.float64)
    acc = dyn.acceleration(q, v)
    np.testing.assert_allclose(acc.numpy(), scene.acceleration(q.numpy(), v.numpy()), rtol=1e-9, atol=1e-9)
    T, V = dyn.energies(q, v)
    T_true, V_true = scene.true_energy_parts(torch.cat([q, v], -1).numpy())
    np.testing.assert_allclose(T.numpy(), T_true, rtol=1e-10)
    np.testing.assert_allclose(V.numpy(), V_true, rtol=1e-10)


@pytest.mark.parametrize("integrator,tol", [("rk4", 1e-4), ({"name": "implicit_midpoint", "order": 4}, 1e-3)])
def test_nonlinear_reparametrisation_is_pulled_back_exactly(scene, integrator, tol):
    """With φ = Σ u_i f_i(q̃), θ = f(q̃(t)) must follow the double pendulum: tests c̃ and ∂T̃/∂q̃ of the modal kinetic energy."""
    emb = ModeMapEmbedding(scene.mode_values, nonlinear=True)
    dyn = _dynamics(scene, nonlinear=True)
    q0 = torch.tensor([[0.2, -0.3], [0.5, 0.1]], dtype=torch.float64)
    v0 = torch.tensor([[0.4, 0.1], [-0.5, 0.3]], dtype=torch.float64)
    theta0 = emb.map(q0)
    omega0 = torch.stack([torch.autograd.functional.jacobian(lambda x: emb.map(x[None])[0], q) @ v
                          for q, v in zip(q0, v0)])
    times = 0.01 * np.arange(101)
    ref = scene.simulate(torch.cat([theta0, omega0], -1).numpy(), times)
    traj = get_integrator(integrator).integrate(dyn, q0, v0, 0.01, 100)
    theta = emb.map(traj.q.reshape(-1, 2)).reshape(2, -1, 2).numpy()
    assert np.abs(theta - ref[..., :2]).max() < tol


def test_ground_truth_conserves_energy(scene, rng):
    states0 = scene.sample_initial_states(3, rng)
    states = scene.simulate(states0, 0.05 * np.arange(101))
    energy = scene.true_energy(states)
    assert np.abs(energy - energy[:, :1]).max() / scene.energy_scale < 1e-8
    q, qdot = scene.fields(states[:, :2], np.array([[0.1, 0.2], [-0.5, 0.7]]))
    assert q.shape == (3, 2, 2, 1) and qdot.shape == q.shape


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="scene.masses"):
        LiftedDoublePendulum(masses=(1.0,))
    with pytest.raises(ValueError, match=r"scene.lengths\[1\]"):
        LiftedDoublePendulum(lengths=(1.0, -1.0))
    with pytest.raises(ValueError, match="scene.modes"):
        LiftedDoublePendulum(modes=((3, 4), (3, 4)))


def test_release_at_rest_puts_both_links_at_the_amplitude_with_no_kinetic_energy(scene):
    state = scene.released_at_rest(0.7)
    np.testing.assert_array_equal(state, [0.7, 0.7, 0.0, 0.0])
    kinetic, potential = scene.true_energy_parts(state)
    assert kinetic == 0 and potential > scene.true_energy_parts(scene.released_at_rest(0.0))[1]
