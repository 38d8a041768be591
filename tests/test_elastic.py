"""The hyperelastic cantilever: FEM model, continuum potential, non-conservative forces (small sizes)."""
import numpy as np
import pytest
import torch
from torch.func import grad, vmap

from lnf.baselines.pod import LinearEmbedding
from lnf.dynamics import ReducedDynamics
from lnf.quadrature import gauss_legendre_rule
from lnf.scenes.elastic import ElasticCantilever
from lnf.fem.materials import StVenantKirchhoff


@pytest.fixture
def scene():
    return ElasticCantilever(mesh=(10, 4))


def test_affine_field_fem_and_continuum_energies_agree(scene):
    """For u = A X both the FEM and the SIREN-side continuum potential are exact: |B| W(I + A) + gravity."""
    A = np.array([[0.05, -0.02], [0.03, 0.04]])
    u = (scene.body.nodes @ A.T)[None]
    area = scene.length * scene.height
    expected = area * float(StVenantKirchhoff(scene.lam, scene.mu).energy_density(torch.eye(2) + torch.as_tensor(A)))
    np.testing.assert_allclose(scene.body.strain_energy(u), expected, rtol=1e-10)
    quad = gauss_legendre_rule([4, 4], scene.bounds).to(torch.float64)
    q = (quad.points @ torch.as_tensor(A).T)[None]
    G = torch.as_tensor(A).expand(1, len(quad.points), 2, 2)
    gravity = scene.rho * scene.gravity * float(quad.weights @ q[0, :, 1])
    V = scene.potential(quad)(q, G)
    np.testing.assert_allclose(V.item(), expected + gravity, rtol=1e-10)
    # the FEM's gravity potential is the same integral (row-sum lumping is exact for linear fields)
    _, potential = scene.true_energy_parts(scene.pack(u, np.zeros_like(u), np.zeros((1, 2))))
    np.testing.assert_allclose(potential, expected + gravity, rtol=1e-10)


def test_potential_gradient_closed_form_matches_autograd(scene, rng):
    quad = gauss_legendre_rule([3, 2], scene.bounds).to(torch.float64)
    q = torch.as_tensor(0.1 * rng.standard_normal((2, len(quad.points), 2)))
    G = torch.as_tensor(0.1 * rng.standard_normal((2, len(quad.points), 2, 2)))
    pot = scene.potential(quad)
    auto = vmap(grad(lambda a, b: pot(a[None], b[None])[0], argnums=(0, 1)))(q, G)
    closed = pot.gradient(q, G)
    torch.testing.assert_close(closed[0], auto[0])
    torch.testing.assert_close(closed[1], auto[1])


def test_verlet_conserves_energy_and_keeps_the_clamp(scene, rng):
    states0 = scene.sample_initial_states(3, rng)
    states = scene.simulate(states0, 0.05 * np.arange(21))
    energy = scene.true_energy(states)
    assert np.abs(energy - energy[:, :1]).max() < 0.02 * scene.energy_scale
    u, v, _ = scene.unpack(states)
    assert np.abs(u[:, :, scene.body.clamped]).max() == 0.0
    assert np.abs(u[:, -1]).max() > 1e-3  # it moves


def test_damping_dissipates_energy(rng):
    scene = ElasticCantilever(mesh=(10, 4), damping=1.0)
    states = scene.simulate(scene.sample_initial_states(3, rng), 0.05 * np.arange(21))
    energy = scene.true_energy(states)
    assert (np.diff(energy, axis=1) < 1e-9 * scene.energy_scale).all()
    assert (energy[:, -1] < energy[:, 0]).all()
    assert scene.controls(states[:, 0]).shape == (3, 2)


def test_fields_interpolate_nodal_values(scene, rng):
    states = scene.sample_initial_states(2, rng)
    u, v, _ = scene.unpack(states)
    q, qdot = scene.fields(states, scene.body.nodes[:7])
    np.testing.assert_allclose(q, u[:, :7], atol=1e-12)
    np.testing.assert_allclose(qdot, v[:, :7], atol=1e-12)
    with pytest.raises(ValueError, match=r"2·2·55 \+ 2 = 222 entries"):
        scene.unpack(states[:, :-1])


def test_reduced_damping_force_is_minus_alpha_mass_velocity(rng):
    """With a linear embedding, τ̃ = Σ w Jᵀ(−α ρ J v) = −α M̃ v, so the damped acceleration differs by −α v."""
    damped = ElasticCantilever(mesh=(4, 2), damping=0.7, load_amplitude_range=(0.0, 0.0))
    free = ElasticCantilever(mesh=(4, 2))
    assert free.capabilities()["damping"] and free.with_damping(0.7).params() == damped.params()
    assert free.with_damping(0.7).is_conservative is False and free.damping == 0.0  # a copy; the scene unchanged
    with pytest.raises(ValueError, match="damping rate"):
        free.with_damping(-1.0)
    emb = LinearEmbedding(damped.bounds, latent_dim=2, out_dim=2, degree=2).double()
    with torch.no_grad():
        emb.modes.copy_(0.1 * torch.as_tensor(rng.standard_normal(emb.modes.shape)))
    quad = gauss_legendre_rule([4, 4], damped.bounds).to(torch.float64)
    q = torch.as_tensor(rng.standard_normal((3, 2)))
    v = torch.as_tensor(rng.standard_normal((3, 2)))
    a_damped = ReducedDynamics(emb.jet, damped, quad).acceleration(q, v)
    a_free = ReducedDynamics(emb.jet, free, quad).acceleration(q, v)
    torch.testing.assert_close(a_damped - a_free, -0.7 * v)


def test_bad_parameters_are_named():
    with pytest.raises(ValueError, match="scene.poisson"):
        ElasticCantilever(poisson=0.5)
    with pytest.raises(ValueError, match="scene.mesh"):
        ElasticCantilever(mesh=(10,))
    with pytest.raises(ValueError, match="scene.deflection_range"):
        ElasticCantilever(deflection_range=(0.1, -0.1))
    with pytest.raises(ValueError, match="scene.release"):
        ElasticCantilever(release="tip")


def test_modal_release_is_an_equilibrium_that_excites_one_mode(rng):
    """The modal release is at rest under gravity plus K_t δ φ₁; its linear part is δ φ₁, and released it keeps
    the fast modes nearly at rest, where the Euler–Bernoulli shape (not an FEM equilibrium) does not."""
    small = dict(mesh=(12, 4), tip_speed_range=(0.0, 0.0), deflection_range=(-0.05, 0.05))
    modal = ElasticCantilever(release="modal", **small)
    u_g, mode, _ = modal.modal_reference()
    assert mode[modal._tip, 1].mean() == pytest.approx(1.0)
    K = modal.body.tangent_stiffness(u_g)
    Km = (K @ mode.reshape(-1)).reshape(-1, 2)[~modal.body.clamped]
    ratio = Km / (modal.nodal_mass[~modal.body.clamped, None] * mode[~modal.body.clamped])  # ω₁² everywhere
    big = np.abs(mode[~modal.body.clamped]) > 0.05 * np.abs(mode).max()
    np.testing.assert_allclose(ratio[big], np.median(ratio[big]), rtol=1e-6)
    for delta in (0.01, 0.002):  # nonlinear remainder O(δ²)
        u0 = modal.modal_release(np.array([delta]))[0]
        assert np.abs(u0 - u_g - delta * mode).max() < 30 * delta**2
    # released at rest from tip deflections up to 0.05 m, over one period: velocity outside span φ₁ (the
    # modal release's share grows like δ: the nonlinear slaving of the other modes)
    times = 0.05 * np.arange(25)
    weight = np.sqrt(np.repeat(modal.nodal_mass, 2))

    def outside(scene):
        states = scene.simulate(scene.sample_initial_states(2, np.random.default_rng(1)), times)
        _, v, _ = scene.unpack(states)
        v = v.reshape(-1, v.shape[-2] * 2) * weight
        m = mode.reshape(-1) * weight
        return np.linalg.norm(v - np.outer(v @ m / (m @ m), m)) / np.linalg.norm(v)

    shape = ElasticCantilever(release="shape", **small)
    assert outside(modal) < 0.06 < 0.2 < outside(shape)


def test_field_gradients_are_exact_for_an_affine_displacement(scene, rng):
    """The bilinear interpolant reproduces u = A X + b, so its gradient is A anywhere in B."""
    A = np.array([[0.05, -0.02], [0.03, 0.04]])
    u = (scene.body.nodes @ A.T + np.array([0.01, -0.02]))[None]
    _, v0, load = scene.unpack(scene.sample_initial_states(1, rng))
    states = scene.pack(u, v0, load)
    points = rng.random((9, 2)) * np.array([scene.length, scene.height])
    G = scene.field_gradients(states, points)
    assert G.shape == (1, 9, 2, 2)
    np.testing.assert_allclose(G[0], np.broadcast_to(A, (9, 2, 2)), atol=1e-12)


def test_field_and_velocity_gradients_match_differences_of_the_interpolated_fields(scene, rng):
    states = scene.sample_initial_states(2, rng)
    points = np.array([[0.31, 0.13], [0.77, 0.29]])  # inside cells, away from their edges
    G, Gv = scene.field_gradients(states, points), scene.velocity_gradients(states, points)
    assert np.abs(Gv).max() > 0 and not np.allclose(G, Gv)
    h = 1e-6
    for j in range(2):
        step = np.zeros(2)
        step[j] = h
        up, v_up = scene.fields(states, points + step)
        down, v_down = scene.fields(states, points - step)
        np.testing.assert_allclose(G[..., j], (up - down) / (2 * h), atol=1e-7)
        np.testing.assert_allclose(Gv[..., j], (v_up - v_down) / (2 * h), atol=1e-7)


def test_release_at_rest_has_the_asked_tip_deflection_no_velocity_and_no_load(scene):
    """The stability study's high-energy states: at rest, unloaded, the tip moved by the amplitude from the
    amplitude-0 release (the first mode's linear response, so within a few % at small deflections)."""
    rest, released = scene.released_at_rest(0.0), scene.released_at_rest(0.05)
    u0, v0, load0 = scene.unpack(rest)
    u, v, load = scene.unpack(released)
    assert released.shape == (4 * scene.n_nodes + 2,)
    assert np.all(v == 0) and np.all(v0 == 0) and load[0] == 0 and load0[0] == 0
    assert scene.true_energy_parts(released)[0] == 0
    assert np.mean(u[scene._tip, 1] - u0[scene._tip, 1]) == pytest.approx(0.05, rel=0.05)
