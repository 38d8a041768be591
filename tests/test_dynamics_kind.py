"""Each dynamics class declares what it is and needs (lnf.dynamics_kind); code asks it, never its name."""
import pytest

from lnf.dynamics_kind import LAGRANGIAN, LEARNED, TABULATED, DynamicsKind, dynamics_kind


@pytest.mark.parametrize("target, kind", [("lnf.dynamics.ReducedDynamics", LAGRANGIAN),
                                          ("lnf.tabulated.TabulatedDynamics", TABULATED),
                                          ("lnf.baselines.latent_mlp.LatentMLPDynamics", LEARNED)])
def test_each_dynamics_class_declares_its_kind(target, kind):
    assert dynamics_kind({"_target_": target}) is kind


def test_the_kinds_say_what_they_need():
    assert LAGRANGIAN.pulled_back and not LAGRANGIAN.needs_codes and not LAGRANGIAN.trained
    assert TABULATED.pulled_back and TABULATED.needs_codes and not TABULATED.trained
    assert not LEARNED.pulled_back and LEARNED.needs_codes and LEARNED.trained


class Undeclared:
    """A dynamics class of a user's own that forgot its kind."""


class Declared:
    kind = DynamicsKind("mine", pulled_back=False, needs_codes=True, trained=True)


def test_a_class_of_ones_own_is_asked_too():
    assert dynamics_kind({"_target_": f"{__name__}.Declared"}).name == "mine"
    with pytest.raises(ValueError, match=r"dynamics._target_=.*Undeclared: Undeclared declares no dynamics kind"):
        dynamics_kind({"_target_": f"{__name__}.Undeclared"})


def test_no_dynamics_kind_is_read_off_a_target_string():
    """The issue that made this module: `_target_` suffix tests in model, evaluate, train and utils."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "lnf"
    offenders = [f"{p.relative_to(root)}" for p in root.rglob("*.py")
                 if any(f'endswith("{name}")' in p.read_text() or f"endswith(('{name}'" in p.read_text()
                        for name in ("ReducedDynamics", "TabulatedDynamics", "LagrangianNeuralField"))]
    assert offenders == []
