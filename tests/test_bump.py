"""The bump carried along a pendulum's arc: on its manifold the field Lagrangian is the pendulum."""
import numpy as np
import pytest
import torch
from torch.func import grad, vmap

from lnf.quadrature import gauss_legendre_rule
from lnf.scenes.bump import BumpPendulum


@pytest.fixture
def scene():
    return BumpPendulum()


def test_the_manifold_lagrangian_is_the_pendulum(scene):
    quad = gauss_legendre_rule(32, scene.bounds).to(torch.float64)
    theta = np.linspace(-2.5, 2.5, 11)
    q, qdot = scene.fields(np.stack([theta, np.ones_like(theta)], -1), quad.points.numpy())
    V = scene.potential(quad)(torch.as_tensor(q)).numpy()
    np.testing.assert_allclose(V, scene.energy_scale * (1 - np.cos(theta)), atol=1e-4 * scene.energy_scale)
    T = 0.5 * scene.omega0_density * np.einsum("bn,n->b", qdot[..., 0] ** 2, quad.weights.numpy())
    np.testing.assert_allclose(T, 0.5 * scene.inertia, rtol=1e-4)  # ½ mℓ² θ̇² with θ̇ = 1


def test_velocity_field_is_the_time_derivative(scene):
    pts = np.array([[0.1, -0.4], [0.3, -0.2], [-0.2, -0.5]])
    state = np.array([[0.7, 1.3]])
    h = 1e-6
    q_plus = scene.fields(state + [[h * 1.3, 0]], pts)[0]
    q_minus = scene.fields(state - [[h * 1.3, 0]], pts)[0]
    np.testing.assert_allclose(scene.fields(state, pts)[1], (q_plus - q_minus) / (2 * h), rtol=1e-6, atol=1e-9)


def test_potential_gradient_closed_form_matches_autograd(scene):
    quad = gauss_legendre_rule(8, scene.bounds).to(torch.float64)
    q = torch.as_tensor(scene.fields(np.array([[0.4, 0.0], [-1.0, 0.0]]), quad.points.numpy())[0])
    pot = scene.potential(quad)
    auto = vmap(grad(lambda a: pot(a[None])[0]))(q)
    torch.testing.assert_close(pot.gradient(q)[0], auto)


def test_bump_must_fit_in_the_body():
    with pytest.raises(ValueError, match="scene.radius"):
        BumpPendulum(radius=0.8, width=0.2)
    with pytest.raises(ValueError, match="scene.width"):
        BumpPendulum(width=-0.1)
