"""What the benchmark studies ask a scene (Scene.baselines, Scene.expensive_reference, Scene.stability_cases):
the built-in experiments' declarations reproduce the tables the studies used to key by scene name, a scene of
one's own gets sensible defaults, and no study names a built-in scene."""
import ast
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from experiments import studylib
from lnf.scenes.base import DiscretePotential, GeneralizedForce, Scene, StabilityCases

ROOT = Path(__file__).resolve().parents[1]

EXPERIMENTS = ("pendulum", "double_pendulum", "bump", "elastic", "elastic_actuated")

# The tables the studies keyed by experiment name before the scenes declared them (experiments/studylib.py's
# UNSUPPORTED and FEM_SCENES, experiments/stability.py's HIGH_ENERGY), written out as the expected values.
OLD_UNSUPPORTED = {"full_order": {"double_pendulum", "elastic", "elastic_actuated"}, "latent_mlp": {"elastic_actuated"}}
OLD_FEM_SCENES = {"elastic", "elastic_actuated"}
_OLD_PENDULUM = dict(levels=(0.5, 0.7, 0.85, 0.95, 0.99), xlabel="θ0 / π (released at rest; 1 = separatrix)",
                     train_edge=0.5, train_text="training range |θ0| ≤ π/2", rotation=(0.0, 7.0), unit=np.pi)
_OLD_ELASTIC = dict(levels=(0.15, 0.2, 0.25, 0.3, 0.4), xlabel="tip deflection of the release at rest δ [m]",
                    train_edge=0.15, train_text="training range |δ| ≤ 0.15 m", rotation=None, unit=1.0)
OLD_HIGH_ENERGY = {
    "pendulum": _OLD_PENDULUM,
    "bump": _OLD_PENDULUM,
    "double_pendulum": dict(levels=(0.5, 0.7, 0.85, 0.95, 0.99), xlabel="θ1(0) = θ2(0) = θ0, at rest: θ0 / π",
                            train_edge=0.5, train_text="training range |θ_i| ≤ π/2", rotation=None, unit=np.pi),
    "elastic": _OLD_ELASTIC,
    "elastic_actuated": _OLD_ELASTIC,
}


def _study(experiment, name="stability"):
    return studylib.Study(name=name, scene=experiment, mode="smoke", out=ROOT / "outputs" / "unused", threads=1)


def test_the_built_in_experiments_are_the_five_of_the_old_tables_and_the_soft_body():
    assert {p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml")} == set(EXPERIMENTS) | {"soft_body"}


def test_the_soft_body_declares_what_the_studies_ask():
    """A 3-D finite-element body: no nodal full-order baseline (2-D bodies only), an expensive reference, and high
    energy releases scaled to its own training range."""
    from lnf.scenes import SoftBody

    scene = SoftBody(box=(0.5, 0.15, 0.1), cells=(4, 2, 1))
    assert scene.baselines() == {"full_order": False, "latent_mlp": True, "pod": True}
    assert scene.expensive_reference and scene.capabilities()["release_at_rest"]
    cases = scene.stability_cases()
    assert cases.train_edge == 0.05 and cases.levels[0] == 0.05 and cases.levels[-1] > 2 * 0.05


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_declarations_of_the_built_in_scenes_reproduce_the_old_tables(experiment):
    study = _study(experiment)
    scene = study.scene_object()  # as the studies build it: from the composed experiment config
    for method in studylib.METHODS:
        assert study.supports(method) == (experiment not in OLD_UNSUPPORTED.get(method, set())), method
    assert scene.baselines() == {"full_order": experiment not in OLD_UNSUPPORTED["full_order"],
                                 "latent_mlp": experiment not in OLD_UNSUPPORTED["latent_mlp"], "pod": True}
    assert scene.expensive_reference is (experiment in OLD_FEM_SCENES)
    assert scene.stability_cases() == StabilityCases(**OLD_HIGH_ENERGY[experiment])
    assert scene.capabilities()["release_at_rest"]


def test_the_default_scene_keeps_the_old_command_and_output_folder():
    """Without --scene a study runs the training config's default scene, prints no --scene and writes into
    outputs/studies/<study>; any other scene is named in both."""
    default, _ = studylib.parse_args("pareto", "", [])
    assert default.scene == "pendulum" and default.is_default_scene()
    assert default.out == ROOT / "outputs" / "studies" / "pareto"
    assert default.command() == "python -m experiments.pareto"
    other, _ = studylib.parse_args("pareto", "", ["--scene", "bump", "--smoke"])
    assert not other.is_default_scene() and other.out.name == "pareto-smoke-bump"
    assert other.command() == "python -m experiments.pareto --smoke --scene bump"


# ---------------------------------------------------------------------------------------------------------
# a scene of one's own: only the required core, then one optional part at a time
# ---------------------------------------------------------------------------------------------------------
class Spring(DiscretePotential):
    def __init__(self, weights):
        self.weights = weights

    def __call__(self, q, G=None):
        return 0.5 * torch.einsum("n,bna->b", self.weights.to(q), q**2)


class Membrane(Scene):
    """The required core only: a field on a 2-D body with a quadratic potential."""

    field_dim = 1
    bounds = [[0.0, 1.0], [0.0, 1.0]]
    energy_scale = 1.0

    def density(self, points):
        return torch.ones(points.shape[:-1], dtype=points.dtype)

    def potential(self, quadrature):
        return Spring(quadrature.weights)

    def params(self):
        return {}


class Rod(Membrane):
    bounds = [[0.0, 1.0]]


class StrainSpring(Spring):
    needs_gradient = True

    def __call__(self, q, G=None):
        return 0.5 * torch.einsum("n,bnad->b", self.weights.to(q), G**2)


class StretchedMembrane(Membrane):
    def potential(self, quadrature):
        return StrainSpring(quadrature.weights)


class Push(GeneralizedForce):
    def field_force(self, t, q, v, controls):
        return controls[:, None, :1].expand_as(q) * torch.ones_like(q)


class DrivenMembrane(Membrane):
    def generalized_force(self, quadrature):
        return Push(quadrature.weights)

    def controls(self, states):
        return np.asarray(states)[..., -1:]


def test_a_scene_with_only_the_required_core_gets_sensible_defaults():
    scene = Membrane()
    assert scene.baselines() == {"full_order": True, "latent_mlp": True, "pod": True}
    assert scene.expensive_reference is False and scene.stability_cases() is None and not scene.has_controls
    # the full-order model needs a 2-D body and a potential of the values alone
    assert Rod().baselines() == {"full_order": False, "latent_mlp": True, "pod": True}
    assert StretchedMembrane().baselines()["full_order"] is False
    # per-trajectory loads: the black box cannot take them, the nodal model has no forces
    driven = DrivenMembrane()
    assert driven.has_controls and not driven.is_conservative
    assert driven.baselines() == {"full_order": False, "latent_mlp": False, "pod": True}


def test_a_scene_overrides_its_declarations_and_the_studies_follow():
    from experiments import stability

    class Costly(Membrane):
        expensive_reference = True

        def baselines(self):
            return {**super().baselines(), "pod": False}

        def released_at_rest(self, amplitude):
            return np.array([amplitude, 0.0])

        def stability_cases(self):
            return StabilityCases((1.0, 2.0), "amplitude", 1.0, "training range ≤ 1")

    study = _study("pendulum")
    study._scene = Costly()  # what scene_object() returns: the studies ask it, never the experiment's name
    assert [m for m in studylib.METHODS if study.supports(m)] == ["lnf", "latent_mlp", "full_order"]
    assert stability.methods(study) == ["lnf", "latent_mlp", "full_order"]
    cases = stability.stress_cases(study)
    assert cases.levels == (1.0, 2.0) and np.allclose(cases.states(study.scene_object(), 2.0), [2.0, 0.0])
    study._scene = Membrane()
    assert stability.stress_cases(study) is None and stability.methods(study) == list(studylib.METHODS)


# ---------------------------------------------------------------------------------------------------------
# no study names a built-in scene
# ---------------------------------------------------------------------------------------------------------
STUDIES = ("studylib/study.py", "studylib/jobs.py", "studylib/results.py", "studylib/charts.py", "studylib/tables.py",
           "stability.py", "pareto.py", "cost_scaling.py", "sparse_noisy.py", "model_size.py", "roofline.py")
_NAME = re.compile(r"(?<![A-Za-z0-9])(" + "|".join(sorted(EXPERIMENTS, key=len, reverse=True)) + r")(?![A-Za-z0-9])",
                   re.IGNORECASE)


def _docstrings(tree):
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                if isinstance(first.value.value, str):
                    out.add(id(first.value))
    return out


def scene_names_in_code(source):
    """(line, text) of each string literal (docstrings aside; f-string parts included) that contains a built-in
    experiment's name as a word, and of each identifier with one as an `_`-separated part (`ELASTIC_CASES`).
    Comments are not in the syntax tree."""
    tree = ast.parse(source)
    skip = _docstrings(tree)
    hits = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
            if _NAME.search(node.value):
                hits.append((node.lineno, node.value))
        names = {ast.Name: lambda n: [n.id], ast.Attribute: lambda n: [n.attr], ast.arg: lambda n: [n.arg],
                 ast.FunctionDef: lambda n: [n.name], ast.ClassDef: lambda n: [n.name],
                 ast.alias: lambda n: [n.asname or n.name]}.get(type(node), lambda n: [])(node)
        for name in names:
            if set(name.lower().split("_")) & set(EXPERIMENTS) or name.lower() in EXPERIMENTS:
                hits.append((node.lineno, name))
    return hits


def test_the_name_check_finds_names_in_code_but_not_in_docstrings_or_comments():
    source = ('"""The pendulum study."""\n'
              'def f(study):\n'
              '    """On the elastic scenes."""\n'
              '    # the bump\n'
              '    ELASTIC_CASES = 1\n'
              '    return study.scene == "pendulum" or f"--scene {study.scene}" == "x double_pendulum"\n')
    assert sorted(line for line, _ in scene_names_in_code(source)) == [5, 6, 6]


@pytest.mark.parametrize("name", STUDIES)
def test_no_study_names_a_built_in_scene(name):
    hits = scene_names_in_code((ROOT / "experiments" / name).read_text())
    assert not hits, f"experiments/{name} names built-in scenes in code (ask the scene object instead): {hits}"
