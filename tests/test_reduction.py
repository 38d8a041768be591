"""The reduction ρ̃, velocity projection and the training losses."""
import pytest
import torch

from lnf.model import LagrangianNeuralField
from lnf.quadrature import midpoint_grid
from lnf.reduction import projection_loss, pullback_mass_matrix, reduce
from lnf.scenes import LiftedPendulum


def _model(latent_dim=1, seed=0):
    torch.manual_seed(seed)
    return LagrangianNeuralField(LiftedPendulum(), latent_dim=latent_dim, width=32, hyper_init_scale=1.0).double()


def _safe_step(model, codes, points):
    """α = 1/L for ℓ^r near `codes` (L = largest Hessian eigenvalue of the Gauss–Newton model)."""
    J = model.field.jet(codes, points, order=1).J[..., 0, :]  # (B, N, d)
    density = model.scene.inertia
    L = (2.0 / points.shape[0]) * density * torch.linalg.eigvalsh(J.transpose(1, 2) @ J).max()
    return 0.5 / L


@pytest.mark.parametrize("latent_dim", [1, 2])
def test_reduction_recovers_decoder_codes(latent_dim):
    model = _model(latent_dim)
    points = midpoint_grid(16, model.scene.bounds).double()
    codes = 0.3 * torch.randn(4, latent_dim, dtype=torch.float64)
    values = model.decode(codes, points)
    alpha = _safe_step(model, codes, points)
    density = model.scene.density(points)
    # start near the answer (ρ̃ is a local method); many steps with a safe α converge to the code
    rec = reduce(model.field, points, values, density, alpha, steps=400, codes=codes + 0.05)
    torch.testing.assert_close(rec, codes, atol=1e-6, rtol=0)


def test_velocity_projection_recovers_latent_velocity():
    model = _model(2)
    points = midpoint_grid(16, model.scene.bounds).double()
    codes = 0.3 * torch.randn(3, 2, dtype=torch.float64)
    v = torch.randn(3, 2, dtype=torch.float64)
    J = model.field.jet(codes, points, order=1).J
    velocities = torch.einsum("bnai,bi->bna", J, v)
    torch.testing.assert_close(model.project_velocity(codes, points, velocities), v)
    # (B, N) scalar fields are accepted too
    torch.testing.assert_close(model.project_velocity(codes, points, velocities[..., 0]), v)


def test_reduce_api_shapes_and_errors():
    model = _model(1)
    points = midpoint_grid(8, model.scene.bounds).double()
    values = torch.randn(5, 64, 1, dtype=torch.float64)
    assert model.reduce(points, values).shape == (5, 1)
    assert model.reduce(points, values[..., 0]).shape == (5, 1)
    with pytest.raises(ValueError, match="NaN or inf"):
        model.reduce(points, values.clone().fill_(float("nan")))
    with pytest.raises(ValueError, match="shape"):
        model.reduce(points, torch.randn(5, 63, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="N ≥ 1"):
        model.reduce(points[:0], values[:, :0])


def test_projection_loss_is_metric_norm():
    codes = torch.tensor([[1.0, 2.0]])
    other = torch.tensor([[0.0, 1.0]])
    mass = torch.tensor([[[2.0, 0.5], [0.5, 1.0]]])
    assert projection_loss(codes, other, mass).item() == pytest.approx(2.0 + 1.0 + 1.0)


def test_losses_are_finite_and_train_both_parts():
    model = _model(1).float()
    points = torch.rand(6, 20, 2) * 2 - 1
    values = torch.randn(6, 20, 1)
    out = model.losses(points, values)
    assert set(out) >= {"reconstruction", "projection", "loss"}
    out["loss"].backward()
    assert model.log_step_size.grad is not None and torch.isfinite(model.log_step_size.grad)
    assert all(p.grad is not None for p in model.field.layers.parameters())


@pytest.mark.parametrize("kwargs,match", [({"reduction_steps": 0}, "reduction_steps"), ({"latent_dim": 0}, "latent_dim"),
                                          ({"step_size": 0.0}, "step_size")])
def test_bad_model_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LagrangianNeuralField(LiftedPendulum(), **kwargs)


def test_velocity_loss_measures_velocity_outside_tangent_space():
    model = LagrangianNeuralField(LiftedPendulum(), latent_dim=1, width=32, velocity_weight=1.0).double()
    points = (torch.rand(3, 40, 2, dtype=torch.float64) * 2 - 1)
    values = model.decode(0.2 * torch.randn(3, 1, dtype=torch.float64), points)
    codes = reduce(model.field, points, values, model.scene.density(points), model.step_size, model.reduction_steps)
    J = model.field.jet(codes, points, order=1).J
    inside = torch.einsum("bnai,bi->bna", J, torch.randn(3, 1, dtype=torch.float64))
    assert model.losses(points, values, inside)["velocity"].item() < 1e-20
    outside = inside + torch.randn_like(inside)
    out = model.losses(points, values, outside)
    assert out["velocity"].item() > 1e-3
    assert out["loss"].item() == pytest.approx(
        (out["reconstruction"] + out["projection"] + out["velocity"]).item(), rel=1e-6)
    # weight 0 is the paper's loss: velocities are ignored
    model.velocity_weight = 0.0
    assert "velocity" not in model.losses(points, values, outside)


def test_singular_mass_matrix_gives_nan_not_a_crash():
    from lnf.reduction import solve_mass

    mass = torch.tensor([[[2.0]], [[0.0]]])
    out = solve_mass(mass, torch.tensor([[4.0], [1.0]]))
    assert out[0].item() == 2.0 and torch.isnan(out[1]).all()


def test_start_grid():
    from lnf.reduction import start_grid

    assert torch.equal(start_grid(2, 1, 1.0), torch.zeros(1, 2))
    grid = start_grid(2, 3, 0.5)
    assert grid.shape == (9, 2) and grid.abs().max() == 0.5 and (grid == 0).all(1).sum() == 1


@pytest.mark.parametrize("batched_points", [False, True])
def test_best_start_is_the_candidate_of_least_reconstruction_loss(batched_points):
    from lnf.reduction import best_start, reconstruction_loss, start_grid

    model = _model(1)
    points = midpoint_grid(8, model.scene.bounds).double()
    codes = torch.tensor([[-0.9], [0.1], [0.7]], dtype=torch.float64)
    values = model.decode(codes, points)
    starts = start_grid(1, 9, 1.0).double()
    density = model.scene.density(points)
    if batched_points:
        points, density = points.expand(3, -1, -1), density.expand(3, -1)
    chosen = best_start(model.field, points, values, density, starts)
    for b in range(3):
        losses = torch.stack([reconstruction_loss(model.field(s[None], points if not batched_points else points[b:b + 1]),
                                                  values[b:b + 1], density if not batched_points else density[b:b + 1])[0]
                              for s in starts])
        assert chosen[b] == starts[losses.argmin()]
    assert torch.equal(chosen, starts[(codes - starts.T).abs().argmin(1)])  # here: the nearest candidate


def test_multi_start_reduction_finds_a_code_far_from_zero():
    """With q̃ far from 0 a few steps from 0 stay far; starting from the best of a grid lands on it."""
    model = _model(1)
    points = midpoint_grid(16, model.scene.bounds).double()
    codes = torch.tensor([[2.6], [-2.2]], dtype=torch.float64)
    values = model.decode(codes, points)
    far = LagrangianNeuralField(LiftedPendulum(), latent_dim=1, width=32, hyper_init_scale=1.0, reduction_starts=41,
                                start_radius=3.0).double()
    far.load_state_dict(model.state_dict())
    assert (model.reduce(points, values) - codes).abs().min() > 1.0
    assert (far.reduce(points, values) - codes).abs().max() < 0.08
    with pytest.raises(ValueError, match="reduction_starts"):
        LagrangianNeuralField(LiftedPendulum(), reduction_starts=0)


def test_training_reprojection_starts_from_the_snapshot_start():
    """In `losses` ρ̃(φ(q̃)) reuses the snapshot's start (one search per step); far from q̃ = 0 that gives the
    projection loss of a fresh search, where starting from 0 would leave the codes far off."""
    model = _model(1)
    points = midpoint_grid(16, model.scene.bounds).double()
    codes = torch.tensor([[2.6], [-2.2]], dtype=torch.float64)
    values = model.decode(codes, points)
    far = LagrangianNeuralField(LiftedPendulum(), latent_dim=1, width=32, hyper_init_scale=1.0, reduction_starts=41,
                                start_radius=3.0).double()
    far.load_state_dict(model.state_dict())
    batched = points.expand(2, -1, -1)
    out = far.losses(batched, values)
    reduced = far.reduce(batched, values)
    assert torch.equal(out["codes"], reduced)
    jet = far.field.jet(reduced, batched, order=1)
    weights = far._density(batched) * 4.0 / points.shape[0]  # the scene's body is [−1, 1]²
    expected = projection_loss(reduced, far.reduce(batched, jet.value), pullback_mass_matrix(jet.J, weights))
    assert torch.allclose(out["projection"], expected.mean(), rtol=1e-8, atol=1e-14)
    assert out["projection"] < 1e-3


def test_the_shared_first_jet_leaves_losses_and_gradients_unchanged():
    """Training reuses the jet at the start codes for both reductions (ρ̃(q) and ρ̃(φ(q̃))): the losses and every
    parameter gradient equal those of two independent reductions."""
    from lnf.model import LagrangianNeuralField
    from lnf.reduction import projection_loss, pullback_mass_matrix, reconstruction_loss, reduce
    from lnf.scenes import LiftedPendulum

    torch.manual_seed(0)
    scene = LiftedPendulum()
    model = LagrangianNeuralField(scene, width=24, hyper_width=8, reduction_steps=3, velocity_weight=0.0).double()
    points = torch.rand(3, 40, 2, dtype=torch.float64) * 2 - 1
    values = torch.randn(3, 40, 1, dtype=torch.float64)
    out = model.losses(points, values)
    grads = torch.autograd.grad(out["loss"], list(model.parameters()))

    density = model._density(points)
    codes = reduce(model.field, points, values, density, model.step_size, 3)
    jet = model.field.jet(codes, points, order=1)
    weights = 4.0 * density / points.shape[-2]
    again = reduce(model.field, points, jet.value, density, model.step_size, 3)
    ref = (reconstruction_loss(jet.value, values, density)
           + projection_loss(codes, again, pullback_mass_matrix(jet.J, weights))).mean()
    torch.testing.assert_close(out["loss"], ref, rtol=1e-12, atol=1e-14)
    for g, r in zip(grads, torch.autograd.grad(ref, list(model.parameters()))):
        torch.testing.assert_close(g, r, rtol=1e-10, atol=1e-12)
