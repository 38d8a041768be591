"""A 3-D body trains, evaluates and draws (bodies of any dimension): a cube whose field is one standing wave of
the 3-D wave equation, L = ½∫q̇² − ½∫|∇_X q|², with its exact solution as the full-order reference."""
import numpy as np
import pytest
import torch
from omegaconf import open_dict

from helpers import TINY, compose_config
from lnf.scenes import DiscretePotential, Scene


class GradientEnergy(DiscretePotential):
    """V = ½ Σ_j w_j |∇_X q_j|²: q (B, N, 1), G (B, N, 1, 3) → (B,)."""

    needs_gradient = True

    def __init__(self, weights):
        self.weights = weights

    def __call__(self, q, G=None):
        return 0.5 * torch.einsum("bnad,n->b", G ** 2, self.weights.to(G))


class StandingWave3D(Scene):
    """q = a(t) sin(πx) sin(πy) sin(πz) on [0, 1]³, ω = π√3; state (a, ȧ)."""

    field_dim, bounds = 1, [[0.0, 1.0]] * 3
    omega = np.pi * np.sqrt(3.0)
    energy_scale = 0.5 * omega ** 2 * 0.125 * 0.1 ** 2  # ½ ω² a² ∫ sin² at a = 0.1

    def params(self):
        return {}

    def density(self, points):
        return torch.ones(points.shape[:-1], dtype=points.dtype)

    def potential(self, quadrature):
        return GradientEnergy(quadrature.weights)

    def sample_initial_states(self, n, rng):
        return np.c_[rng.uniform(-0.1, 0.1, n), rng.uniform(-0.1, 0.1, n) * self.omega]

    def simulate(self, initial, times):
        wt = self.omega * times[None, :]
        a0, v0 = initial[:, :1], initial[:, 1:]
        return np.stack([a0 * np.cos(wt) + v0 / self.omega * np.sin(wt), -a0 * self.omega * np.sin(wt) + v0 * np.cos(wt)], -1)

    def fields(self, states, points):
        shape = np.prod(np.sin(np.pi * points), axis=-1)  # (N,)
        return states[..., None, :1] * shape[:, None], states[..., None, 1:] * shape[:, None]

    def field_gradients(self, states, points):
        s, c = np.sin(np.pi * points), np.cos(np.pi * points)
        grad = np.pi * np.stack([c[:, 0] * s[:, 1] * s[:, 2], s[:, 0] * c[:, 1] * s[:, 2], s[:, 0] * s[:, 1] * c[:, 2]], -1)
        return states[..., None, :1, None] * grad[:, None, :]  # (..., N, 1, 3)

    def true_energy_parts(self, states):
        return 0.0625 * states[..., 1] ** 2, 0.0625 * self.omega ** 2 * states[..., 0] ** 2


@pytest.mark.slow
def test_a_3d_body_trains_evaluates_and_draws_its_middle_slice(tmp_path):
    from lnf.scenes.check import check_scene
    from lnf.train import train

    assert check_scene(StandingWave3D()).ok
    cfg = compose_config("train", [*TINY, "data.fine_resolution=6", "data.coarse_resolution=6", "quadrature.order=3",
                                   "model.latent_dim=1", "trainer=smoke", "trainer.max_epochs=1", "logger=csv",
                                   "threads=1", "evaluation.val_resolution=4"], tmp_path)
    with open_dict(cfg):
        cfg.scene = {"_target_": f"{__name__}.StandingWave3D"}
    metrics = train(cfg)
    assert metrics["evaluation_points"] == 216 and metrics["epochs_run"] == 1
    assert np.isfinite(metrics["projection_rel_l2/all/median"]) and "energy_rel_err/max" in metrics
    assert (tmp_path / "out" / "figures" / "test_trajectory0.png").stat().st_size > 0
