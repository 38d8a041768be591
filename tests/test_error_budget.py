"""Reading the test error against the projection floor (lnf.error_budget)."""
import math

from lnf.error_budget import read_error_budget


def _m(floor, error, window="all"):
    return {f"projection_rel_l2/{window}/median": floor, f"field_rel_l2/{window}/median": error}


def test_a_collapsed_embedding_is_named_with_its_floor():
    (finding,) = read_error_budget(_m(0.99, 1.2))
    assert "the embedding collapsed" in finding and "0.99" in finding and "model.w0" in finding


def test_dynamics_that_lose_the_accuracy_are_named_with_the_ratio():
    (finding,) = read_error_budget(_m(0.022, 0.181))
    assert "the dynamics lose the accuracy" in finding and "8.23× the projection floor 0.022" in finding


def test_a_diverged_rollout_over_a_good_floor_points_at_the_dynamics():
    (finding,) = read_error_budget(_m(0.01, math.inf))
    assert "the rollout diverged" in finding and "0.01" in finding


def test_nothing_stands_out_near_the_floor_or_without_a_floor():
    assert read_error_budget(_m(0.0169, 0.0182)) == []
    assert read_error_budget({"field_rel_l2/all/median": 0.5}) == []
    assert read_error_budget(_m(float("nan"), 0.5)) == []
    assert read_error_budget(_m(0.01, 0.1, "extrapolation"), window="extrapolation")


def test_stiff_dynamics_are_named_and_the_clamp_blamed_only_on_a_clamped_field():
    metrics = {**_m(0.01, 0.012), "substeps": 40.0}
    (plain,) = read_error_budget(metrics)
    (clamped,) = read_error_budget(metrics, clamped=True)
    assert "stiff" in plain and "40 integration steps per sample" in plain and "clamp" not in plain
    assert "model.clamp=false" in clamped
    assert read_error_budget({**metrics, "substeps": 2.0}, clamped=True) == []  # a few substeps: nothing to say


def test_a_closure_is_suggested_only_to_a_model_without_one():
    (bare,) = read_error_budget(_m(0.022, 0.181))
    (closed,) = read_error_budget(_m(0.022, 0.181), closed=True)
    assert "model.closure_degree=4" in bare
    assert "closure" not in closed and "the integrator's order 4" in closed


def test_a_collapsed_embedding_gets_the_advice_its_model_gives():
    """POD-Galerkin has no SIREN frequency: its collapse names its own settings, not model.w0."""
    from lnf.baselines.full_order import FullOrderModel
    from lnf.baselines.pod import PODGalerkin
    from lnf.model import LagrangianNeuralField

    (pod,) = read_error_budget(_m(1.19, 1.19), collapse_advice=PODGalerkin.collapse_advice)
    assert "model.latent_dim" in pod and "model.w0" not in pod
    (grid,) = read_error_budget(_m(0.9, 0.9), collapse_advice=FullOrderModel.collapse_advice)
    assert "model.resolution" in grid and "model.w0" not in grid
    (ours,) = read_error_budget(_m(0.9, 0.9), collapse_advice=LagrangianNeuralField.collapse_advice)
    assert "model.w0" in ours
