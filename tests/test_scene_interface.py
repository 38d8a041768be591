"""The Scene as an explicit interface: required core, optional parts, declared capabilities, check_scene,
importable specs."""
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from lnf.model import build
from lnf.scenes import BumpPendulum, ElasticCantilever, LiftedDoublePendulum, LiftedPendulum, Scene
from lnf.scenes.base import DiscretePotential, SceneMethodMissing
from lnf.scenes.check import SceneCheckError, check_scene


class _HalfSquare(DiscretePotential):
    """V = ½ k Σ_j w_j q_j²."""

    def __init__(self, weights, k):
        self.weights, self.k = weights, k

    def __call__(self, q, G=None):
        return 0.5 * self.k * torch.einsum("bn,n->b", q[..., 0] ** 2, self.weights.to(q))


class StandingWave(Scene):
    """q(X, t) = a(t) sin(πX) on B = [0, 1] with ω0 = 1 and V = ½k∫q²: a(t) is a harmonic oscillator, ω² = k."""

    field_dim, bounds = 1, [[0.0, 1.0]]

    def __init__(self, k: float = 4.0):
        self.k, self.energy_scale = float(k), 0.25 * float(k)

    def params(self):
        return {"k": self.k}

    def density(self, points):
        return torch.ones(points.shape[:-1], dtype=points.dtype)

    def potential(self, quadrature):
        return _HalfSquare(quadrature.weights, self.k)

    def sample_initial_states(self, n, rng):
        return rng.uniform(-1, 1, size=(n, 2))

    def simulate(self, initial_states, times):
        w = np.sqrt(self.k)
        a0, v0 = initial_states[:, None, 0], initial_states[:, None, 1]
        a = a0 * np.cos(w * times) + v0 / w * np.sin(w * times)
        v = -a0 * w * np.sin(w * times) + v0 * np.cos(w * times)
        return np.stack([a, v], axis=-1)

    def fields(self, states, points):
        mode = np.sin(np.pi * points[:, 0])[:, None]  # (N, 1)
        return states[..., 0, None, None] * mode, states[..., 1, None, None] * mode

    def true_energy_parts(self, states):
        return 0.25 * states[..., 1] ** 2, 0.25 * self.k * states[..., 0] ** 2


def test_a_correct_user_scene_passes_check_scene_and_declares_what_it_has():
    scene = StandingWave()
    report = check_scene(scene)
    assert report.ok and len(report.passed) == 8, str(report)
    caps = scene.capabilities()
    assert caps["simulator"] and caps["fields"] and caps["true_energies"] and caps["conservative"]
    assert not caps["release_at_rest"] and not caps["clamp"] and not caps["kinetic_correction"]


@pytest.mark.parametrize("scene", [LiftedPendulum(), LiftedDoublePendulum(), BumpPendulum()], ids=lambda s: s.name)
def test_built_in_scenes_pass_check_scene(scene):
    assert check_scene(scene).ok


def test_the_elastic_scene_declares_whether_forces_act():
    assert ElasticCantilever().capabilities()["conservative"]
    damped = ElasticCantilever(damping=0.5)
    assert not damped.capabilities()["conservative"] and damped.capabilities()["clamp"]


class _NoScale(Scene):
    field_dim, bounds = 1, [[0.0, 1.0]]


def test_a_missing_required_attribute_names_the_scene_and_the_attribute():
    with pytest.raises(AttributeError, match=r"_NoScale sets no energy_scale"):
        _NoScale().energy_scale
    assert _NoScale().name == "_noscale"


def test_a_missing_optional_part_names_the_scene_and_the_method():
    class Trajectories(StandingWave):  # trained from stored trajectories: no simulator
        simulate = Scene.simulate

    with pytest.raises(SceneMethodMissing, match=r"scene 'trajectories' \(.*Trajectories\) does not define simulate\(\)"):
        Trajectories().simulate(np.zeros((1, 2)), np.arange(3.0))
    assert not Trajectories().capabilities()["simulator"]
    report = check_scene(Trajectories())
    assert report.ok and any("simulator" in s for s in report.skipped)
    with pytest.raises(SceneMethodMissing, match="released_at_rest"):
        StandingWave().released_at_rest(0.5)


class _Bad(StandingWave):
    def density(self, points):
        return -torch.ones(points.shape[:-1], dtype=points.dtype)


class _WrongUnits(StandingWave):
    def true_energy_parts(self, states):
        kin, pot = super().true_energy_parts(states)
        return kin, 2 * pot  # twice V: V and the reference energies disagree


class _Leaky(StandingWave):
    def simulate(self, initial_states, times):
        states = super().simulate(initial_states, times)
        return states * np.exp(-0.5 * times)[None, :, None]  # loses energy though no force is declared


class _NotBatched(StandingWave):
    def fields(self, states, points):
        q, v = super().fields(states, points)
        return q.reshape(-1, len(points), 1), v.reshape(-1, len(points), 1)


@pytest.mark.parametrize("scene, problem", [
    (_Bad(), r"density must be finite and > 0"),
    (_WrongUnits(), r"V of the scene's own fields .* differs from true_energy_parts' potential"),
    (_Leaky(), r"total energy drifts by .* though the scene declares no forces"),
    (_NotBatched(), r"fields\(states \(n, T, S\), points \(N, dim_B\)\) must return q, q̇ of shape"),
], ids=["density", "units", "conservation", "broadcasting"])
def test_check_scene_says_what_to_fix(scene, problem):
    with pytest.raises(SceneCheckError, match=problem):
        check_scene(scene)


def test_a_scene_of_a_script_run_as_a_module_records_its_module_not_main(tmp_path):
    (tmp_path / "my_wave.py").write_text(textwrap.dedent('''
        import json
        from lnf.scenes import Scene

        class Wave(Scene):
            field_dim, bounds, energy_scale = 1, [[0.0, 1.0]], 1.0

            def params(self):
                return {}

        if __name__ == "__main__":
            print(json.dumps(Wave().spec()))
    '''))
    run = [sys.executable, "-m", "my_wave"]
    out = subprocess.run(run, cwd=tmp_path, capture_output=True, text=True, check=True).stdout
    assert json.loads(out)["_target_"] == "my_wave.Wave"
    by_path = subprocess.run([sys.executable, "my_wave.py"], cwd=tmp_path, capture_output=True, text=True)
    assert by_path.returncode != 0 and "Put it in an importable module" in by_path.stderr


def test_a_scene_that_cannot_be_imported_names_its_module_and_the_fix():
    with pytest.raises(ValueError, match=r"cannot import module 'my_lab_scenes\.strings'.*PYTHONPATH"):
        build({"_target_": "my_lab_scenes.strings.VibratingString"})
    with pytest.raises(ValueError, match=r"module 'lnf\.scenes' .* has no 'Strings'"):
        build({"_target_": "lnf.scenes.Strings"})


def test_settings_a_model_does_not_take_are_dropped_with_a_warning(caplog):
    """+experiment=double_pendulum model=pod: the experiment's SIREN width used to be a TypeError in POD."""
    import logging

    from lnf.model import build_model

    with caplog.at_level(logging.WARNING, logger="lnf.model"):
        model = build_model({"_target_": "lnf.scenes.LiftedPendulum"},
                            {"_target_": "lnf.baselines.pod.PODGalerkin", "latent_dim": 1, "width": 128},
                            {"_target_": "lnf.quadrature.GaussLegendre"})
    assert type(model).__name__ == "PODGalerkin"
    assert caplog.text.count("PODGalerkin takes no model.width: dropped") == 1


class _HalfGradientSquare(DiscretePotential):
    """V = ½ k Σ_j w_j (∂q/∂X)_j²: a potential of ∇_X q."""

    needs_gradient = True

    def __init__(self, weights, k):
        self.weights, self.k = weights, k

    def __call__(self, q, G=None):
        return 0.5 * self.k * torch.einsum("bn,n->b", G[..., 0, 0] ** 2, self.weights.to(G))


class _StrainWithoutGradients(StandingWave):
    """A potential of ∇_X q, and no field_gradients(): only the gradient loss needs those."""

    def potential(self, quadrature):
        return _HalfGradientSquare(quadrature.weights, self.k)


def test_check_scene_demands_field_gradients_only_where_the_run_needs_them():
    report = check_scene(_StrainWithoutGradients())
    assert report.ok, str(report)
    assert any("field_gradients" in s and "gradient_weight" in s for s in report.skipped)
    with pytest.raises(SceneCheckError, match=r"field_gradients: model\.gradient_weight=0\.1 \(the gradient loss\) "
                                              r"needs field_gradients\(\), which .*_StrainWithoutGradients does not"):
        check_scene(_StrainWithoutGradients(),
                    needs={"field_gradients": "model.gradient_weight=0.1 (the gradient loss)"})
    with pytest.raises(ValueError, match=r"unknown capabilities \['gradients'\]"):
        check_scene(StandingWave(), needs=["gradients"])


class _BumpWithScaledGradients(BumpPendulum):
    """∇_X q off by 1 %: what a subclass that inherits or mistypes field_gradients() would give."""

    def field_gradients(self, states, points):
        return 1.01 * super().field_gradients(states, points)


@pytest.mark.parametrize("scene", [LiftedPendulum(), BumpPendulum()], ids=["pendulum", "bump"])
def test_the_pendulum_scenes_give_the_gradients_of_their_own_fields(scene):
    report = check_scene(scene, needs=["field_gradients"])
    assert any("against central differences" in p for p in report.passed), str(report)


def test_check_scene_rejects_field_gradients_that_are_not_the_gradients_of_fields():
    with pytest.raises(SceneCheckError, match=r"field_gradients differs from central differences of fields by "
                                              r"0\.01\d* of the largest gradient"):
        check_scene(_BumpWithScaledGradients(), needs=["field_gradients"])


def test_check_scene_names_the_methods_of_each_capability_the_run_needs():
    class Trajectories(StandingWave):  # no simulator
        simulate = Scene.simulate
        sample_initial_states = Scene.sample_initial_states

    assert check_scene(Trajectories()).ok
    with pytest.raises(SceneCheckError, match=r"simulator: this run needs simulate\(\) and sample_initial_states\(\)"):
        check_scene(Trajectories(), needs=["simulator"])
    report = check_scene(StandingWave(), needs=["simulator", "fields", "true_energies"], simulate=False)
    assert report.ok and any("simulate=False" in s for s in report.skipped)


def _untrained_model():
    from lnf.model import LagrangianNeuralField

    torch.manual_seed(0)
    return LagrangianNeuralField(StandingWave(), latent_dim=1, width=16, hyper_width=8)


def test_float64_codes_and_fields_are_taken_and_come_back_in_the_models_dtype():
    """NumPy's float64 used to stop reduce, rollout and decode with torch's 'mat1 and mat2 must have the same dtype'."""
    model = _untrained_model()
    points = torch.linspace(0.05, 0.95, 16, dtype=torch.float64)[:, None]
    values = 0.3 * torch.sin(np.pi * points)[None].repeat(2, 1, 1)
    q0 = model.reduce(points, values)
    v0 = model.project_velocity(q0.double(), points, values)
    assert q0.dtype == v0.dtype == torch.float32
    traj = model.rollout(q0.double(), v0.double(), dt=0.05, steps=3)
    assert traj.q.dtype == torch.float32 and torch.isfinite(traj.q).all()
    fields = model.decode(traj.q[:, -1].double().numpy(), points.numpy())
    assert fields.dtype == torch.float32 and fields.shape == (2, 16, 1)
    assert torch.allclose(fields, model.decode(traj.q[:, -1], points.float()))
    kinetic, potential = model.energy(traj.q.double(), traj.v.double())
    assert kinetic.dtype == potential.dtype == torch.float32


def test_decode_outside_the_bodys_bounds_warns_once_per_call_or_refuses():
    import warnings

    from lnf.reduced_model import OutsideBodyWarning

    model = _untrained_model()
    codes = torch.zeros(1, 1)
    points = torch.tensor([[-0.5], [0.0], [0.5], [1.0], [1.5], [2.0]])
    outside = r"decode: 3 of 6 points lie outside the body's bounds \[\[0\.0, 1\.0\]\]"
    with pytest.warns(OutsideBodyWarning, match=outside) as caught:
        model.decode(codes, points)
    assert len(caught) == 1
    with pytest.raises(ValueError, match=r"3 of 6 points lie outside the body's bounds"):
        model.decode(codes, points, outside="error")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.decode(codes, points, outside="ignore")
        model.decode(codes, points[1:4])  # inside, the ends included: no warning
