"""Baselines: POD-Galerkin (linear special case of our model), full-order model, black-box latent MLP."""
import numpy as np
import pytest
import torch

from lnf.baselines import FullOrderModel, LatentMLPDynamics, LegendreBasis, PODGalerkin
from lnf.baselines.pod import LinearEmbedding
from lnf.dynamics import ReducedDynamics
from lnf.quadrature import gauss_legendre_rule, midpoint_grid
from lnf.scenes.pendulum import LiftedPendulum


def _observations(scene, n=6, T=30, n_obs=200, dt=0.05, seed=0):
    """Masked observations (n, Nobs, 2), (n, T, Nobs, 1) of true trajectories, plus their states (n, T, 2)."""
    rng = np.random.default_rng(seed)
    times = dt * np.arange(T)
    states = scene.simulate(scene.sample_initial_states(n, rng), times)
    grid = midpoint_grid(32, scene.bounds).numpy()
    idx = np.stack([rng.choice(len(grid), n_obs, replace=False) for _ in range(n)])
    points = grid[idx]
    values = np.stack([scene.fields(states[i], points[i])[0] for i in range(n)])
    return torch.as_tensor(points), torch.as_tensor(values), states


def test_legendre_basis_is_orthonormal_and_its_gradient_matches_finite_differences():
    basis = LegendreBasis([[-1.0, 2.0], [0.0, 1.0]], degree=5)
    quad = gauss_legendre_rule(8, [[-1.0, 2.0], [0.0, 1.0]])
    B = basis.values(quad.points.numpy())
    gram = B.T @ (quad.weights.numpy()[:, None] * B)
    np.testing.assert_allclose(gram, np.eye(basis.size), atol=1e-12)
    x = np.array([[0.3, 0.4], [1.7, 0.9]])
    eps = 1e-6
    for k in range(2):
        e = np.zeros(2)
        e[k] = eps
        fd = (basis.values(x + e) - basis.values(x - e)) / (2 * eps)
        np.testing.assert_allclose(basis.gradients(x)[..., k], fd, atol=1e-6)


def test_pod_is_exact_at_one_mode_on_the_lifted_pendulum():
    scene = LiftedPendulum()
    points, values, states = _observations(scene)
    pod = PODGalerkin(scene, latent_dim=1)
    info = pod.fit_to_observations(points, values)
    assert info["pod_energy_captured"] > 1 - 1e-9
    X = torch.rand(500, 2, dtype=torch.float64) * 2 - 1
    zero = torch.zeros(1, 1, dtype=torch.float64)
    mode = pod.double().field.jet(zero, X, order=1).J[0, :, 0, 0]
    u = torch.as_tensor(scene.mode(X.numpy()))
    assert torch.allclose(mode.abs(), u.abs(), atol=1e-6)  # the mode is ±u anywhere, not only on the data points
    # its dynamics are the shared pulled-back ReducedDynamics, with M̃ = mℓ² (orthonormal mode)
    dyn = pod.dynamics()
    assert isinstance(dyn, ReducedDynamics)
    assert torch.allclose(dyn.mass_matrix(torch.zeros(3, 1, dtype=torch.float64)), torch.ones(3, 1, 1, dtype=torch.float64),
                          atol=1e-8)


def test_pod_rollout_reproduces_the_true_pendulum():
    scene = LiftedPendulum()
    points, values, states = _observations(scene)
    pod = PODGalerkin(scene, latent_dim=1).double()
    pod.fit_to_observations(points, values)
    grid = midpoint_grid(24, scene.bounds).double()
    q_true, v_true = scene.fields(states[:, 0], grid.numpy())
    q0 = pod.reduce(grid, torch.as_tensor(q_true))
    v0 = pod.project_velocity(q0, grid, torch.as_tensor(v_true))
    traj = pod.rollout(q0, v0, dt=0.05, steps=29, integrator="rk4")
    pred = pod.decode(traj.q.reshape(-1, 1), grid).reshape(len(states), 30, -1)
    true = torch.as_tensor(scene.fields(states, grid.numpy())[0][..., 0])
    assert float((pred - true).norm() / true.norm()) < 1e-5


def test_pod_needs_fitting_and_rejects_bad_input():
    scene = LiftedPendulum()
    pod = PODGalerkin(scene, latent_dim=2)
    with pytest.raises(RuntimeError, match="fit_to_observations"):
        pod.reduce(torch.zeros(4, 2), torch.zeros(1, 4, 1))
    with pytest.raises(ValueError, match="latent_dim"):
        PODGalerkin(scene, latent_dim=0)
    with pytest.raises(ValueError, match="points .* and values"):
        pod.fit_to_observations(torch.zeros(3, 5, 2), torch.zeros(3, 5, 1))


def _quadratic_embedding(seed=0):
    """A LinearEmbedding on [0, 2] × [0, 1] (degree 4, 2 components, d = 2) with random m, Φ and symmetric Ψ."""
    gen = torch.Generator().manual_seed(seed)
    field = LinearEmbedding([[0.0, 2.0], [0.0, 1.0]], 2, 2, 4).double()
    nb = field.basis.size
    quad = torch.randn(nb, 2, 2, 2, generator=gen, dtype=torch.float64)
    field.set_subspace(torch.randn(nb, 2, generator=gen, dtype=torch.float64),
                       torch.randn(nb, 2, 2, generator=gen, dtype=torch.float64), quad + quad.transpose(-1, -2))
    points = torch.rand(3, 5, 2, generator=gen, dtype=torch.float64) * torch.tensor([2.0, 1.0], dtype=torch.float64)
    return field, points, torch.randn(3, 2, generator=gen, dtype=torch.float64)


def test_quadratic_embedding_jet_matches_finite_differences_in_codes_and_space():
    field, points, codes = _quadratic_embedding()
    jet = field.jet(codes, points, order=2, spatial=True)
    eps = 1e-6
    step = lambda k, n: eps * torch.eye(n, dtype=torch.float64)[k]  # noqa: E731
    J = torch.stack([(field(codes + step(i, 2), points) - field(codes - step(i, 2), points)) / (2 * eps)
                     for i in range(2)], -1)
    H = torch.stack([(field.jet(codes + step(i, 2), points).J - field.jet(codes - step(i, 2), points).J) / (2 * eps)
                     for i in range(2)], -1)
    G = torch.stack([(field(codes, points + step(k, 2)) - field(codes, points - step(k, 2))) / (2 * eps)
                     for k in range(2)], -1)
    GJ = torch.stack([(field.jet(codes, points + step(k, 2)).J - field.jet(codes, points - step(k, 2)).J) / (2 * eps)
                      for k in range(2)], -2)
    for name, fd, exact in (("J", J, jet.J), ("H", H, jet.H), ("G", G, jet.G), ("GJ", GJ, jet.GJ)):
        assert torch.allclose(fd, exact, atol=1e-5 * exact.abs().max()), name
    # the same on one set of points shared by the batch (to rounding: a shared and a batched product may take
    # different BLAS kernels, whose sums differ in the last bits on some CPUs)
    shared = field.jet(codes, points[0], order=2, spatial=True)
    expanded = field.jet(codes, points[0].expand(3, 5, 2).clone(), order=2, spatial=True)
    for name in ("value", "J", "H", "G", "GJ"):
        a, b = getattr(shared, name), getattr(expanded, name)
        assert a.shape == b.shape and torch.allclose(a, b, rtol=1e-12, atol=1e-12 * b.abs().max()), name


def test_linear_embedding_basis_cache_never_serves_freed_points():
    # points freed and reallocated at the same address must not read the old points' basis
    field, points, codes = _quadratic_embedding()
    for shift in (0.01, 0.02, 0.03, 0.04):
        moved = points + shift
        fresh = LinearEmbedding([[0.0, 2.0], [0.0, 1.0]], 2, 2, 4).double()
        fresh.set_subspace(field.mean, field.modes, field.quad)
        assert torch.equal(field(codes, moved), fresh(codes, moved))
        del moved


def test_a_linear_embedding_saved_before_the_quadratic_part_loads_with_psi_zero():
    field, points, codes = _quadratic_embedding()
    old = {k: v for k, v in field.state_dict().items() if k != "quad"}  # a checkpoint of an earlier lnf
    fresh = LinearEmbedding([[0.0, 2.0], [0.0, 1.0]], 2, 2, 4).double()
    fresh.load_state_dict(old)
    assert not fresh.quad.any()
    linear = LinearEmbedding([[0.0, 2.0], [0.0, 1.0]], 2, 2, 4).double()
    linear.set_subspace(field.mean, field.modes)
    assert torch.equal(fresh(codes, points), linear(codes, points))


def test_quadratic_manifold_recovers_a_quadratic_family_of_fields():
    # frames m + Φ q + Ψ[q, q] with Ψ orthogonal to Φ: the fit finds most of Ψ, and the frames far better than POD
    scene = LiftedPendulum()
    basis = LegendreBasis(scene.bounds, 6)
    rng = np.random.default_rng(0)
    nb = basis.size
    orth, _ = np.linalg.qr(rng.standard_normal((nb, 4)))
    mean, modes, psi = 0.1 * orth[:, 0], orth[:, 1:3], orth[:, 3]
    q = rng.uniform(-1, 1, (4, 40, 2)) * np.array([1.0, 0.3])
    coeffs = mean + q @ modes.T + 0.5 * (q[..., 0] * q[..., 1])[..., None] * psi  # (4, 40, nb)
    points = np.stack([midpoint_grid(16, scene.bounds).numpy()] * 4)
    values = np.einsum("inb,itb->itn", np.stack([basis.values(p) for p in points]), coeffs)[..., None]
    pod = PODGalerkin(scene, latent_dim=2, degree=6, quadratic=True, quadratic_ridge=1e-10).double()
    info = pod.fit_to_observations(torch.as_tensor(points), torch.as_tensor(values))
    # the sample's POD modes are not exactly Φ (the quadratic part is not exactly uncorrelated with q in it)
    assert info["quadratic_explained"] > 0.95
    pts, vals = torch.as_tensor(points[0]), torch.as_tensor(values[0])
    linear = PODGalerkin(scene, latent_dim=2, degree=6).double()
    linear.fit_to_observations(torch.as_tensor(points), torch.as_tensor(values))
    error = {name: float((m.field(m.reduce(pts, vals), pts) - vals).norm() / vals.norm())
             for name, m in (("quadratic", pod), ("linear", linear))}
    assert error["quadratic"] < 0.2 * error["linear"], error
    with pytest.raises(ValueError, match="quadratic_ridge"):
        PODGalerkin(scene, quadratic=True, quadratic_ridge=-1.0)


def test_full_order_model_integrates_the_scene_on_its_nodes():
    scene = LiftedPendulum()
    fom = FullOrderModel(scene, resolution=48).double()
    nodes = fom.nodes.double()
    states0 = np.array([[1.2, 0.3], [-0.4, -1.0]])
    q, v = scene.fields(states0, nodes.numpy())
    q0 = fom.reduce(nodes, torch.as_tensor(q))
    assert torch.equal(q0, torch.as_tensor(q)[..., 0])  # on its own nodes the state is the field itself
    v0 = fom.project_velocity(q0, nodes, torch.as_tensor(v))
    traj = fom.rollout(q0, v0, dt=0.05, steps=40, integrator={"name": "implicit_midpoint", "order": 4})
    # exact solution of the discretised system: θ̈ = −(g/ℓ) sin(θ ‖u‖²_h) with the grid's ‖u‖²_h
    u = torch.as_tensor(scene.mode(nodes.numpy()))
    norm2 = float((fom.weights.double() * u * u).sum())
    k = scene.gravity / scene.length
    from scipy.integrate import solve_ivp
    for i, (th, om) in enumerate(states0):
        sol = solve_ivp(lambda t, y: [y[1], -k * np.sin(norm2 * y[0])], (0, 2.0), [th, om], t_eval=[2.0],
                        rtol=1e-11, atol=1e-11)
        theta = float((fom.weights.double() * u * traj.q[i, -1]).sum()) / norm2
        assert theta == pytest.approx(sol.y[0, -1], abs=2e-4)  # 4th-order time error at dt = 0.05
    kin, pot = fom.energy(traj.q, traj.v)
    energy = (kin + pot).numpy()
    assert np.abs(energy - energy[:, :1]).max() < 1e-4 * scene.energy_scale * 10  # bounded O(h⁴) oscillation
    # off the nodes: bilinear interpolation of the nodal field
    X = torch.tensor([[0.1, -0.2], [0.77, 0.5]], dtype=torch.float64)
    pred = fom.decode(q0, X)
    assert torch.allclose(pred[..., 0], torch.as_tensor(scene.fields(states0, X.numpy())[0][..., 0]), atol=2e-2)


def test_latent_mlp_fits_a_known_oscillator_and_refuses_the_symplectic_integrator():
    torch.manual_seed(0)
    t = 0.05 * torch.arange(40)
    amp = torch.linspace(0.5, 1.5, 16)[:, None]
    phase = torch.linspace(0, 3, 16)[:, None]
    q = (amp * torch.sin(2.0 * t + phase))[..., None]
    v = (2.0 * amp * torch.cos(2.0 * t + phase))[..., None]
    mlp = LatentMLPDynamics(latent_dim=1, width=32, iterations=600, lr=1e-2, window=4)
    with pytest.raises(RuntimeError, match="not fitted"):
        mlp.as_dynamics(None)
    info = mlp.fit(q, v, dt=0.05)
    assert info["latent_fit_loss"] < 1e-2
    with torch.no_grad():
        acc = mlp(q.reshape(-1, 1), v.reshape(-1, 1))
    assert float((acc + 4.0 * q.reshape(-1, 1)).abs().mean()) < 0.1 * float((4.0 * q).abs().mean())
    from lnf.integrators import get_integrator

    with pytest.raises(ValueError, match="rk4"):
        get_integrator("implicit_midpoint").integrate(mlp.as_dynamics(None), q[:, 0], v[:, 0], 0.05, 2)
