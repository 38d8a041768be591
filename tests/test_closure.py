"""The potential closure (lnf/closure.py): a polynomial ΔṼ fitted to the residual of the pulled-back equations."""
import dataclasses
import json
import math
import os
import subprocess
import sys
from types import SimpleNamespace

import pytest
import torch

from helpers import METRICS_ONLY, ROOT, TINY, compose_config, run_cli
from lnf.closure import (CLOSURE_MAX_TERMS, CODE_SPAN_FLOOR, ClosedDynamics, PotentialClosure, equation_residual,
                         floored_spans, monomial_exponents)
from lnf.integrators import get_integrator
from test_dynamics import _nonlinear_setup, _pendulum_dynamics


def test_the_monomials_are_every_total_degree_from_two_up():
    assert monomial_exponents(2, 3).tolist() == [[1, 0], [0, 1], [2, 0], [1, 1], [0, 2], [3, 0], [2, 1], [1, 2], [0, 3]]
    assert len(monomial_exponents(4, 4)) == 4 + 10 + 20 + 35
    with pytest.raises(ValueError, match=r"closure_degree must be 0 \(no closure\) or ≥ 2, got 1"):
        PotentialClosure(2, 1)


def test_the_closures_degree_is_lowered_until_it_has_at_most_its_most_terms():
    """Degree 4 keeps 4 at d = 1, 2 (4 and 14 terms) and becomes 2 at d = 3, 4 (9 and 14 terms, not 34 and 69);
    never below 2; no cap where none is given (a checkpoint written before the cap rebuilds its shapes)."""
    import yaml

    kept = {d: PotentialClosure(d, 4, 14) for d in (1, 2, 3, 4, 5)}
    assert {d: (c.degree, len(c.coef)) for d, c in kept.items()} == {1: (4, 4), 2: (4, 14), 3: (2, 9), 4: (2, 14),
                                                                    5: (2, 20)}
    assert PotentialClosure(3, 4).degree == 4 and len(PotentialClosure(3, 4).coef) == 34
    assert len(PotentialClosure(3, 4, 19).coef) == 19  # degree 3 fits 19 terms exactly
    with pytest.raises(ValueError, match=r"model.closure_max_terms must be null \(no cap\) or ≥ 1, got 0"):
        PotentialClosure(3, 4, 0)
    # the training's and lnf.evaluate's defaults are the library's
    for name, key in (("model/lnf.yaml", "closure_max_terms"), ("evaluate.yaml", "closure_max_terms")):
        assert yaml.safe_load((ROOT / "conf" / name).read_text())[key] == CLOSURE_MAX_TERMS, name


def test_the_gradient_is_the_potentials_and_a_polynomial_residual_is_fitted_exactly():
    torch.manual_seed(0)
    truth = PotentialClosure(2, 4).double()
    truth.center.copy_(torch.tensor([0.3, -0.2]))
    truth.scale.copy_(torch.tensor([4.5, 5.0]))  # every code inside its box: the polynomial itself
    truth.coef.copy_(torch.randn(len(truth.coef)))
    q = torch.randn(200, 2, dtype=torch.float64, requires_grad=True)
    auto = torch.autograd.grad(truth.potential(q).sum(), q)[0]
    torch.testing.assert_close(truth.gradient(q), auto)
    fitted = PotentialClosure(2, 4).double()
    misfit = fitted.fit(q.detach(), -truth.gradient(q).detach(), 1e-12)
    assert misfit < 1e-6 and fitted.active
    torch.testing.assert_close(fitted.gradient(q), truth.gradient(q), rtol=1e-6, atol=1e-8)
    fitted.reset()
    assert not fitted.active and fitted.potential(q).abs().max() == 0


def test_beyond_the_fitted_box_the_closure_continues_linearly_and_stays_a_gradient():
    """Past the codes it was fitted on, a quartic would carry a rollout away; the closure continues as its first-order
    expansion from the nearest point of the box (a bounded force, continuous across the box's faces), and its force
    is still the exact gradient of its potential there (the closed dynamics stay conservative)."""
    torch.manual_seed(1)
    for d in (1, 2, 3):
        closure = PotentialClosure(d, 4).double()
        closure.center.copy_(torch.linspace(-0.2, 0.3, d))
        closure.scale.copy_(torch.linspace(0.5, 1.5, d))
        closure.coef.copy_(torch.randn(len(closure.coef)))
        q = (closure.center + 3.0 * closure.scale * torch.randn(400, d, dtype=torch.float64)).requires_grad_(True)
        auto = torch.autograd.grad(closure.potential(q).sum(), q)[0]
        torch.testing.assert_close(closure.gradient(q), auto)
        x = (q.detach() - closure.center) / closure.scale
        inside = (x.abs() <= 1).all(-1)
        assert 0 < int(inside.sum()) < len(q)  # both kinds of points
        poly = (x[:, None, :] ** closure.exponents).prod(-1) @ closure.coef  # the polynomial itself
        torch.testing.assert_close(closure.potential(q)[inside], poly[inside])
    edge = PotentialClosure(1, 4).double()
    edge.coef.copy_(torch.tensor([0.0, 1.0, 0.0, -3.0]))  # x² − 3x⁴: runs away past |x| = 1
    far = torch.tensor([[1.0], [2.0], [10.0]], dtype=torch.float64)
    torch.testing.assert_close(edge.gradient(far), torch.full((3, 1), 2.0 - 12.0, dtype=torch.float64))
    torch.testing.assert_close(edge.potential(far), torch.tensor([-2.0, -12.0, -92.0], dtype=torch.float64))


def test_while_a_guard_is_set_codes_beyond_the_fitted_range_get_a_nan_force_row_by_row():
    """The shooting refinement ends a trial trajectory that leaves the training codes (it would pay for a rollout
    crawling off them) and only that one; without a guard the closure rolls out anywhere."""
    closure = PotentialClosure(1, 3).double()
    closure.fit(torch.linspace(-1.0, 1.0, 50)[:, None].double(), torch.randn(50, 1).double(), 1e-8)

    class Base:
        def hamiltonian_derivatives(self, q, p, t=0.0):
            return p, -q

    closed = ClosedDynamics(Base(), closure)
    codes = torch.tensor([[1.4], [1.6], [-1.6]], dtype=torch.float64)
    assert torch.isfinite(closed.hamiltonian_derivatives(codes, codes)[1]).all()  # no guard: anywhere
    closure.set_guard(0.25)  # the fitted range −1 … 1 widened to −1.5 … 1.5
    force = closed.hamiltonian_derivatives(codes, codes)[1]
    assert torch.isfinite(force[0]).all() and torch.isnan(force[1:]).all()
    closure.set_guard(None)
    assert torch.isfinite(closed.hamiltonian_derivatives(codes, codes)[1]).all()


def test_a_barely_moving_commensurate_code_is_scaled_and_guarded_by_a_floor_of_the_largest_span():
    """Where the codes share one unit (POD coordinates), a code that spans 0.3 % of the largest is measured by
    CODE_SPAN_FLOOR of it: its quadratic term is no stiffness of θ/span², and a drift of a few of its own widths, a
    small change of the field, does not end a shooting trial. Without the floor each code keeps its own span."""
    torch.manual_seed(0)
    q = torch.stack([torch.linspace(-2.0, 2.0, 200), 0.006 * torch.linspace(-1.0, 1.0, 200).flip(0)], 1).double()
    residual = torch.randn(200, 2, dtype=torch.float64)
    own, floored = PotentialClosure(2, 2).double(), PotentialClosure(2, 2).double()
    own.fit(q, residual, 1e-8)
    floored.fit(q, residual, 1e-8, span_floor=CODE_SPAN_FLOOR)
    torch.testing.assert_close(own.scale, torch.tensor([2.0, 0.006], dtype=torch.float64))
    torch.testing.assert_close(floored.scale, torch.tensor([2.0, 2.0 * CODE_SPAN_FLOOR], dtype=torch.float64))
    torch.testing.assert_close(floored_spans(torch.tensor([4.0, 0.012]), 0.0), torch.tensor([4.0, 0.012]))
    drift = torch.tensor([[0.0, 0.03]], dtype=torch.float64)  # 5 half-widths of the 2nd code off its centre
    for floor, alive in ((0.0, False), (CODE_SPAN_FLOOR, True)):
        own.set_guard(1.0, floor)
        assert bool(torch.isfinite(own.gradient(drift)).all()) is alive
        own.set_guard(None)


def test_the_closed_pendulum_conserves_its_closed_energy_and_adds_the_closure_force(pendulum):
    base = _pendulum_dynamics(pendulum)
    closure = PotentialClosure(1, 3).double()
    closure.coef.copy_(torch.tensor([0.0, 2.0, -0.5]))  # ΔṼ = 2 q² − 0.5 q³
    closed = ClosedDynamics(base, closure)
    q, v = torch.tensor([[0.4], [-0.2]], dtype=torch.float64), torch.tensor([[0.3], [1.0]], dtype=torch.float64)
    mass = base.mass_matrix(q)[:, 0]
    torch.testing.assert_close(closed.acceleration(q, v),
                               base.acceleration(q, v) - (4 * q - 1.5 * q ** 2) / mass)
    closed.controls = None  # set on the base, as a rollout sets a forced scene's loads
    assert base.controls is None and closed.kind == base.kind
    traj = get_integrator("implicit_midpoint").integrate(closed, q, v, 0.01, 400)
    kinetic, potential = closed.energies(traj.q, traj.v)
    energy = kinetic + potential
    assert (energy - energy[:, :1]).abs().max() < 1e-6 * energy.abs().max()
    plain_kinetic, plain_potential = base.energies(traj.q, traj.v)
    assert (plain_kinetic + plain_potential - energy).abs().max() > 1e-3  # the closure's energy is in it


@pytest.mark.parametrize("integrator", ["rk4", "implicit_midpoint"])
def test_a_closed_2d_system_conserves_its_closed_energy_in_both_forms(integrator):
    _, base, _ = _nonlinear_setup()  # a 2-D pullback with a configuration-dependent mass
    closure = PotentialClosure(2, 3).double()  # a stiffer, slightly anharmonic well
    closure.coef.copy_(torch.tensor([0.0, 0.0, 0.5, 0.1, 0.5, 0.05, 0.0, -0.03, 0.02], dtype=torch.float64))
    closed = ClosedDynamics(base, closure)
    q0 = torch.tensor([[0.3, -0.2], [0.1, 0.4]], dtype=torch.float64)
    v0 = torch.tensor([[0.2, 0.1], [-0.3, 0.2]], dtype=torch.float64)
    traj = get_integrator(integrator).integrate(closed, q0, v0, 0.005, 150)  # the toy runs away after ~1.5 s
    kinetic, potential = closed.energies(traj.q, traj.v)
    energy = kinetic + potential
    assert (energy - energy[:, :1]).abs().max() < 1e-7 * (1 + energy.abs().max())
    assert (sum(base.energies(traj.q, traj.v)) - energy).abs().max() > 1e-3  # the closure's energy is in it


def test_the_residual_of_the_models_own_motion_vanishes_and_another_motions_is_fitted(pendulum):
    base = _pendulum_dynamics(pendulum)
    q0 = torch.tensor([[0.5], [-0.8], [1.1]], dtype=torch.float64)
    dt = 0.01
    own = get_integrator("rk4").integrate(base, q0, torch.zeros_like(q0), dt, 200)
    _, residual = equation_residual(base, own.q, own.v, dt)
    forces = (base.mass_matrix(own.q[:, 0]) @ base.acceleration(own.q[:, 0], own.v[:, 0])[..., None]).abs().max()
    assert residual.abs().max() < 1e-5 * forces  # the stencil's error, (ω dt)⁴/30 of an acceleration
    truth = PotentialClosure(1, 2).double()  # a stiffer spring: motion of base + ΔṼ, explained by ΔṼ
    truth.coef.copy_(torch.tensor([0.0, 3.0]))
    truth.scale.fill_(2.0)  # a polynomial on the box |q̃| ≤ 2 the motion stays in
    other = get_integrator("rk4").integrate(ClosedDynamics(base, truth), q0, torch.zeros_like(q0), dt, 200)
    codes, residual = equation_residual(base, other.q, other.v, dt)
    fitted = PotentialClosure(1, 4).double()
    assert fitted.fit(codes, residual, 1e-10) < 1e-4
    grid = torch.linspace(-0.8, 1.05, 7, dtype=torch.float64)[:, None]  # inside the codes it was fitted on
    torch.testing.assert_close(fitted.gradient(grid), truth.gradient(grid), rtol=1e-3, atol=1e-4)


@pytest.mark.slow
def test_a_run_fits_the_closure_and_its_checkpoint_loads_with_it(tmp_path):
    from lnf import load

    run = tmp_path / "run"
    run_cli(["+experiment=pendulum", "trainer=smoke", "trainer.max_epochs=2", "logger=csv", "threads=1", *TINY,
             "model.closure_degree=3", "evaluation.val_trajectories=1",
             # a two-epoch model's trial closures are stiff: 4 automatic substeps at most, not 64
             "integrator.max_substeps=4",
             # the closure and its metrics are what is checked: no figures, validation epochs or long-horizon check
             *METRICS_ONLY,
             f"hydra.run.dir={run}"], tmp_path)
    metrics = json.loads((run / "metrics.json").read_text())
    for key in ("closure_regularizer", "closure_val_error", "closure_pullback_val_error", "closure_seconds"):
        assert key in metrics
    assert metrics["closure_val_error"] <= metrics["closure_pullback_val_error"]  # never worse on validation
    model = load(run / "checkpoints" / "last.ckpt")
    assert model.closure is not None and len(model.closure.coef) == 3
    assert model.closure.active == (metrics["closure_regularizer"] > 0 or metrics["closure_shooting"] == 1)
    assert isinstance(model.dynamics(), ClosedDynamics) == model.closure.active
    # the ablation script on the same checkpoint: its test errors without and with a closure fitted the same way
    out = tmp_path / "ablation"
    env = {**os.environ, "LNF_ROOT": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-m", "experiments.closure_ablation", "--ckpt",
                           str(run / "checkpoints" / "last.ckpt"), "--degree", "2", "--threads", "1", "--out", str(out),
                           "--shooting-iterations", "0"],  # its shooting: in the run above and the tests below
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    row = json.loads((out / "closure.json").read_text())["rows"][0]
    assert row["degree"] == 2 and set(row["plain"]) == set(row["closed"]) and "after horizon" in (out / "summary.md").read_text()
    # lnf.evaluate fits one on the checkpoint's training trajectories first (here the residual fit alone: no
    # shooting search), and refuses a degree below 2 and a negative shooting budget by name
    evaluated = tmp_path / "evaluated"
    common = [sys.executable, "-m", "lnf.evaluate", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}", "figures=0",
              "threads=1"]
    proc = subprocess.run([*common, "closure_degree=2", "closure_shooting_iterations=0", f"hydra.run.dir={evaluated}"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    fitted = json.loads((evaluated / "metrics.json").read_text())
    assert fitted["closure_val_error"] <= fitted["closure_pullback_val_error"] and "field_rel_l2/all/median" in fitted
    assert fitted["closure_shooting"] == 0 and "closure shooting: none" in proc.stdout + proc.stderr
    # the two refusals in this process (the settings check lnf.evaluate runs first; the script's argument check)
    from experiments import closure_ablation
    from lnf.evaluation_settings import check_settings

    cfg = compose_config("evaluate", [f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}", "closure_degree=1"], tmp_path)
    with pytest.raises(ValueError) as refused:
        check_settings(cfg)
    assert "closure_degree" in str(refused.value) and "≥ 2" in str(refused.value)
    cfg = compose_config("evaluate", [f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}", "closure_degree=2",
                                      "closure_shooting_iterations=-1"], tmp_path)
    with pytest.raises(ValueError, match="closure_shooting_iterations"):
        check_settings(cfg)
    with pytest.raises(SystemExit) as bad:
        closure_ablation.main(["--ckpt", str(tmp_path / "none.ckpt")])
    assert "--ckpt: no such file" in str(bad.value.code)


class _ClosedModel:
    """The part of a ReducedModel that shooting uses: a closure on a fixed base dynamics, rolled out by an integrator."""

    def __init__(self, base, closure, conservative=True):
        self.base, self.closure = base, closure
        self.scene = SimpleNamespace(is_conservative=conservative)  # False: the shooting rolls out each window alone

    def as_model(self, x):
        return x

    def dynamics(self):  # as ReducedModel.dynamics: closed only while the closure is active
        return ClosedDynamics(self.base, self.closure) if self.closure.active else self.base

    def rollout(self, q0, v0, dt, steps, integrator, on_divergence, dynamics, controls=None, t0=0.0):
        return get_integrator(integrator).integrate(dynamics, q0, v0, dt, steps, t0=t0, on_divergence=on_divergence)


def test_shooting_recovers_the_closure_whose_motion_the_codes_follow_from_a_wrong_start(pendulum):
    from lnf.closure_choice import shoot_closure

    base = _pendulum_dynamics(pendulum)
    truth = PotentialClosure(1, 2).double()  # ΔṼ = 3 q²: a stiffer spring than the pullback's
    truth.coef.copy_(torch.tensor([0.0, 3.0]))
    truth.scale.fill_(2.0)  # a polynomial on the box |q̃| ≤ 2 the motion stays in
    q0 = torch.tensor([[0.5], [-0.8], [1.1]], dtype=torch.float64)
    dt = 0.02
    motion = get_integrator("rk4").integrate(ClosedDynamics(base, truth), q0, torch.zeros_like(q0), dt, 150)
    for first in ([0.2, 2.0], [0.0, 0.0]):  # a third too soft and off-centre, or no closure: the phase drifts
        fitted = PotentialClosure(1, 2).double()
        fitted.scale.fill_(2.0)
        fitted.coef.copy_(torch.tensor(first))
        start, end = shoot_closure(_ClosedModel(base, fitted), motion.q, motion.v, dt, None, "rk4")
        assert end < 1e-3 * start
        torch.testing.assert_close(fitted.coef, truth.coef, rtol=1e-4, atol=1e-5)


class _UnitSpring:
    """q̈ = −q (+ the closure's force): a base dynamics whose rollouts cost nothing."""

    def acceleration(self, q, v, t=0.0, extra_force=None):
        return -q if extra_force is None else extra_force - q

    def potential_energy(self, q):
        return 0.5 * (q ** 2).sum(-1)


def test_multiple_shooting_escapes_the_phase_minimum_that_stalls_single_shooting(monkeypatch):
    """Over many periods the whole-window gap has local minima in the frequency (a phase off by whole turns):
    from no closure, single shooting alone settles in one (here ω = 0.5 in place of 2, gap 1.27 of the codes'
    spread); windows of 10 samples, each from its encoded state, see less than a period and find the closure."""
    from lnf import closure_choice

    truth = PotentialClosure(1, 2).double()  # ΔṼ = 1.5 q²: ω² = 1 + 3
    truth.coef.copy_(torch.tensor([0.0, 1.5]))
    truth.scale.fill_(2.0)
    q0 = torch.tensor([[0.5], [-0.8], [1.1]], dtype=torch.float64)
    dt = 0.1
    motion = get_integrator("rk4").integrate(ClosedDynamics(_UnitSpring(), truth), q0, torch.zeros_like(q0), dt, 150)

    def shoot(window, conservative=True):
        monkeypatch.setattr(closure_choice, "SHOOTING_WINDOW", window)
        fitted = PotentialClosure(1, 2).double()
        fitted.scale.fill_(2.0)
        start, end = closure_choice.shoot_closure(_ClosedModel(_UnitSpring(), fitted, conservative), motion.q,
                                                  motion.v, dt, None, "rk4")
        return fitted, start, end

    fitted, start, end = shoot(150)  # one window, the whole training window: single shooting alone
    assert end > 0.5 * start and abs(float(fitted.coef[1]) - 1.5) > 1.0
    for conservative in (True, False):  # the windows as rows of one rollout, or one rollout each (forced scenes)
        fitted, start, end = shoot(10, conservative)
        assert end < 1e-6 * start
        torch.testing.assert_close(fitted.coef, truth.coef, rtol=1e-6, atol=1e-8)


class _LoadedSpring:
    """q̈ = −q + a cos t (+ the closure's force), unit mass; the loads a (B, 1) in `controls`, as a forced scene's."""

    def __init__(self):
        self.controls = None

    def _load(self, t):
        return self.controls[:, :1] * torch.cos(torch.as_tensor(t, dtype=self.controls.dtype))

    def acceleration(self, q, v, t=0.0, extra_force=None):
        force = -q + self._load(t)
        return force if extra_force is None else force + extra_force

    def hamiltonian_derivatives(self, q, p, t=0.0):
        return p, -q + self._load(t)

    def velocity(self, q, p):
        return p

    def momentum(self, q, v):
        return v

    def potential_energy(self, q):
        return 0.5 * (q ** 2).sum(-1)


def test_per_row_closure_coefficients_roll_out_as_separate_closures_through_newtons_row_subsets():
    """One batched rollout whose blocks of rows each carry their own closure coefficients (the shooting's Jacobian)
    gives each block the trajectory of a rollout with that closure alone, loads included, also where a stiff block
    sends only its rows to Newton's method (which hands them `controls` row by row)."""
    from lnf.integrators import ImplicitMidpoint

    thetas = torch.tensor([[0.0, 0.5], [0.1, 2.0], [0.0, 400.0]], dtype=torch.float64)  # the last: ω ≈ 28 at h = 0.1
    q0 = torch.tensor([[0.5], [-0.3]], dtype=torch.float64)
    loads = torch.tensor([[0.2], [-0.4]], dtype=torch.float64)

    def closure(coef):
        c = PotentialClosure(1, 2).double()
        c.scale.fill_(2.0)
        c.coef.copy_(coef)
        return c

    def roll(dynamics, q, rows_loads):
        dynamics.controls = rows_loads
        integ = ImplicitMidpoint(order=2, max_substeps=1)
        return integ.integrate(dynamics, q, torch.zeros_like(q), 0.1, 12, on_divergence="mark"), integ

    batched = ClosedDynamics(_LoadedSpring(), closure(torch.zeros(2)))
    batched.controls = loads.repeat(3, 1)
    batched.set_row_coefficients(thetas.repeat_interleave(2, 0))
    assert batched.controls.shape == (6, 3)  # the loads, then the coefficients
    together, integ = roll(batched, q0.repeat(3, 1), batched.controls)
    assert integ.newton_solves > 0  # the stiff block went to Newton's method
    batched.set_row_coefficients(None)
    torch.testing.assert_close(batched.controls, loads.repeat(3, 1))  # the base keeps its loads
    for k, theta in enumerate(thetas):
        alone, _ = roll(ClosedDynamics(_LoadedSpring(), closure(theta)), q0, loads)
        torch.testing.assert_close(together.q[2 * k:2 * k + 2], alone.q, rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match=r"shape \(6, 2\)"):
        closure(thetas[0]).gradient(q0.repeat(3, 1), thetas)


class _Table(_UnitSpring):
    """A base dynamics that says it is a table of `terms` (per axis) in `d` codes, its coefficients those of a
    conservative table (M̃'s upper triangle and Ṽ, each with its d derivatives): TabulatedDynamics' `small_tensors`
    and `table`."""
    small_tensors = True

    def __init__(self, terms, d):
        size, channels = math.prod(terms), d * (d + 1) // 2 + 1
        self.table = SimpleNamespace(d=d, nodes=tuple(terms), size=size,
                                     coef=torch.zeros(1).expand(size * (1 + d) * channels))  # its count, no memory


@pytest.mark.parametrize("terms, expected", [((128, 128), 16), ((32,) * 3, 4), ((16,) * 4, 4), ((128, 6, 4), 16),
                                             ((48, 8, 8, 4), 4)])
def test_shooting_fits_fewer_trajectories_on_a_table_of_many_nodes(monkeypatch, terms, expected):
    """16 training trajectories on a table whose evaluation costs at most a 128² table's at d = 2 (multiply-adds per
    row: its coefficients), 4 on larger ones: the 32³ and 16⁴ tables, and the soft body's d = 4 table read as 12 288
    terms in 4 codes (676 000 a row); its d = 3 table read as 128 × 6 × 4 terms stays at 16."""
    from lnf import closure_choice

    fitted = PotentialClosure(1, 2).double()
    fitted.scale.fill_(2.0)
    model = _ClosedModel(_Table(terms, len(terms)), fitted)
    q0 = torch.linspace(-0.8, 0.8, 20, dtype=torch.float64)[:, None]
    motion = get_integrator("rk4").integrate(_UnitSpring(), q0, torch.zeros_like(q0), 0.1, 10)
    rows, rollout = set(), model.rollout

    def counted(q0, *a, **k):  # the whole window (one window): trajectories × coefficient vectors rows
        rows.add(len(q0))
        return rollout(q0, *a, **k)

    model.rollout = counted
    monkeypatch.setattr(closure_choice, "SHOOTING_WINDOW", 10)
    closure_choice.shoot_closure(model, motion.q, motion.v, 0.1, None, "rk4", iterations_per_term=1)
    assert min(rows) == expected and all(r % expected == 0 for r in rows)


def test_a_shooting_stage_stops_after_its_budget_of_rollouts_and_keeps_its_best(monkeypatch, caplog):
    """closure_shooting_iterations = k allows k × (m + 1)² coefficient vectors rolled out per stage, m the terms
    counted up to SHOOTING_BUDGET_TERMS, the finite-difference Jacobians' included (scipy's own max_nfev leaves them
    out since 1.16; here each Jacobian is one batched rollout of terms + 1 vectors), and the stage keeps the best
    point it rolled out."""
    from lnf import closure_choice

    truth = PotentialClosure(1, 2).double()
    truth.coef.copy_(torch.tensor([0.0, 1.5]))
    truth.scale.fill_(2.0)
    q0 = torch.tensor([[0.5], [-0.8]], dtype=torch.float64)
    motion = get_integrator("rk4").integrate(ClosedDynamics(_UnitSpring(), truth), q0, torch.zeros_like(q0), 0.1, 40)
    monkeypatch.setattr(closure_choice, "SHOOTING_WINDOW", 10)
    caplog.set_level("INFO", logger="lnf.closure")
    for iterations, counted_terms in ((1, 2), (3, 2), (3, 1)):  # counted_terms 1: the budget stops growing at 1 term
        monkeypatch.setattr(closure_choice, "SHOOTING_BUDGET_TERMS", counted_terms)
        caplog.clear()
        fitted = PotentialClosure(1, 2).double()
        fitted.scale.fill_(2.0)
        model = _ClosedModel(_UnitSpring(), fitted)
        vectors = {10: 0, 40: -3}  # coefficient vectors rolled out per window length (three whole-window gaps:
        rollout = model.rollout  # the start, and after each stage)

        def counted(q0, *a, **k):  # 2 trajectories: 2 rows per vector over the whole window, 8 over 4 windows
            vectors[k["steps"]] += len(q0) // (2 if k["steps"] == 40 else 8)
            return rollout(q0, *a, **k)

        model.rollout = counted
        start, end = closure_choice.shoot_closure(model, motion.q, motion.v, 0.1, None, "rk4", iterations_per_term=iterations)
        budget = iterations * (counted_terms + 1) ** 2  # two terms: up to (2 + 1)² vectors per iteration and term
        if budget < 27:  # the budget binds: the next Jacobian (3 vectors) would pass it, and each stage says so
            assert budget - 3 < vectors[10] <= budget and budget - 3 < vectors[40] <= budget
            assert caplog.text.count(f"of {budget} coefficient vectors rolled out") >= 2
            assert "windows of 10 samples: gap" in caplog.text and "(its budget spent)" in caplog.text
        else:  # more room: more vectors, up to the budget, until the search converges
            assert 9 < vectors[10] <= budget and vectors[40] <= budget
        assert end < start


def test_a_shooting_stage_stops_when_its_gap_stalls(monkeypatch, caplog):
    """A stage whose best gap shrank by less than SHOOTING_STALL over SHOOTING_STALL_ITERATIONS Jacobians stops
    there, well inside its budget, and says so; with no stall rule (0) it goes on to its budget. The search here is
    one that never moves (each iteration a Jacobian at the start), so its gap stalls from the first."""
    from lnf import closure_choice

    def motionless(fun, x0, jac, max_nfev, **kwargs):  # Levenberg–Marquardt that never finds a better point
        fun(x0)
        while True:
            jac(x0)

    q0 = torch.tensor([[0.5], [-0.8]], dtype=torch.float64)
    motion = get_integrator("rk4").integrate(_UnitSpring(), q0, torch.zeros_like(q0), 0.1, 40)
    monkeypatch.setattr(closure_choice, "SHOOTING_WINDOW", 10)
    monkeypatch.setattr(closure_choice, "least_squares", motionless)
    caplog.set_level("INFO", logger="lnf.closure")
    for stall in (closure_choice.SHOOTING_STALL, 0.0):
        monkeypatch.setattr(closure_choice, "SHOOTING_STALL", stall)
        caplog.clear()
        fitted = PotentialClosure(1, 2).double()
        fitted.scale.fill_(2.0)
        fitted.coef.fill_(0.3)
        model = _ClosedModel(_UnitSpring(), fitted)
        vectors, rollout = [0], model.rollout

        def counted(q0, *a, **k):
            if k["steps"] == 10:  # the windows' stage: 2 trajectories × 4 windows rows per vector
                vectors[0] += len(q0) // 8
            return rollout(q0, *a, **k)

        model.rollout = counted
        closure_choice.shoot_closure(model, motion.q, motion.v, 0.1, None, "rk4", iterations_per_term=5)
        budget = 5 * 3 ** 2
        if stall:  # the first trial, then Jacobians of 3 vectors until the one that would follow a stall
            assert vectors[0] == 1 + 3 * closure_choice.SHOOTING_STALL_ITERATIONS
            assert caplog.text.count("stalled: the gap shrank by less than 1% over 3 iterations") == 2
        else:
            assert budget - 3 < vectors[0] <= budget and "(its budget spent)" in caplog.text
            assert "stalled" not in caplog.text


@dataclasses.dataclass
class _FitSpec:
    """What fit_closure reads of an EvaluationSpec, for its tests with stand-in models and data."""
    split: str = "test"
    label: str = ""
    long_steps: int = 0
    figures: int = 0
    keep_fields: int = 0
    progress: bool = False
    closure_shooting_iterations: int = 0


def test_the_closure_fit_reads_a_forced_scenes_loads_where_the_file_stores_none(tmp_path, monkeypatch):
    """A generated actuated cantilever keeps its loads (A, f) in the states, not in a `controls` dataset: the closure's
    residual and shooting must act them, as the evaluation does (they once ran without the actuation)."""
    import numpy as np

    from lnf import closure_choice
    from lnf.dataset import DatasetConfig, generate_dataset, load_split
    from lnf.scenes import ElasticCantilever

    scene = ElasticCantilever(mesh=(4, 2), damping=0.3, load_amplitude_range=(-0.6, 0.6),
                              load_frequency_range=(0.3, 0.7))
    path = generate_dataset(scene, DatasetConfig(n_train=3, n_val=1, n_test=1, n_times=8, dt=0.05, train_times=4,
                                                 fine_resolution=6, coarse_resolution=4, observed_fraction=0.5),
                            tmp_path / "actuated.h5")
    train, val = load_split(path, "train"), load_split(path, "val")
    assert train.controls is None  # nothing stored beside the states
    loads = train.loads(scene)
    np.testing.assert_array_equal(loads, scene.controls(train.states[:, 0]))
    assert loads.shape == (3, 2) and np.abs(loads[:, 0]).max() > 0

    seen = {}

    class Stop(Exception):
        pass

    def residual(dynamics, codes, velocities, dt, t0, controls):
        seen["controls"] = controls
        raise Stop

    codes = torch.zeros(3, 4, 1)
    monkeypatch.setattr(closure_choice, "evaluate_model",
                        lambda model, data, spec: SimpleNamespace(metrics={"field_rel_l2/in_horizon/median": 0.1}))
    monkeypatch.setattr(closure_choice, "latent_trajectories", lambda *args: (codes, codes))
    monkeypatch.setattr(closure_choice, "equation_residual", residual)
    model = SimpleNamespace(closure=PotentialClosure(1, 2), scene=scene, eval=lambda: None, latent_dynamics=None,
                            lagrangian_dynamics=lambda: None)
    datamodule = SimpleNamespace(split={"train": train, "val": val}.__getitem__, dt=0.05,
                                 observations=lambda split: train.observed(4, velocities=True))
    with pytest.raises(Stop):
        closure_choice.fit_closure(model, datamodule, _FitSpec())
    torch.testing.assert_close(seen["controls"], torch.as_tensor(loads))


@pytest.mark.parametrize("floored_wins", [True, False])
def test_where_codes_share_one_unit_a_closure_on_floored_spans_is_a_candidate_chosen_on_validation(monkeypatch,
                                                                                                 floored_wins):
    """A model whose codes share one unit (POD coordinates) gets each residual fit twice, on each code's own span and
    on spans floored at its code_span_floor; the validation picks one, and the closure keeps that one's scale."""

    from lnf import closure_choice

    torch.manual_seed(0)
    t = torch.linspace(0.0, 6.0, 40)
    codes = torch.stack([torch.sin(t), 0.003 * torch.cos(3 * t)], -1)[None].double()  # (1, T, 2): a barely moving 2nd
    residual = torch.randn(40, 2, dtype=torch.float64)
    closure = PotentialClosure(2, 2).double()

    calls = []

    def validation(model, data, spec):  # the floored fits validate better, or worse, than the pure pullback
        calls.append(1)
        floored = bool(closure.active and closure.scale[1] > 0.01)
        err = 0.1 if not closure.active else (0.05 if floored == floored_wins else 0.2)
        return SimpleNamespace(metrics={"field_rel_l2/in_horizon/median": err})

    monkeypatch.setattr(closure_choice, "evaluate_model", validation)
    monkeypatch.setattr(closure_choice.EvaluationData, "of_split",
                        lambda *args: SimpleNamespace(within_horizon=lambda: None))
    monkeypatch.setattr(closure_choice, "latent_trajectories", lambda *args: (codes, codes))
    monkeypatch.setattr(closure_choice, "equation_residual", lambda *args: (codes.reshape(-1, 2), residual))
    model = SimpleNamespace(closure=closure, scene=None, eval=lambda: None, latent_dynamics=None,
                            lagrangian_dynamics=lambda: None, code_span_floor=CODE_SPAN_FLOOR)
    train = SimpleNamespace(loads=lambda scene: None, times=[0.0])
    datamodule = SimpleNamespace(split={"train": train, "val": None}.__getitem__, dt=0.05,
                                 observations=lambda split: (torch.zeros(1), torch.zeros(1), torch.zeros(1)))
    record = closure_choice.fit_closure(model, datamodule, _FitSpec())
    assert record["closure_val_error"] == 0.05 and closure.active
    assert record["closure_span_floor"] == (CODE_SPAN_FLOOR if floored_wins else 0.0)
    spans = (codes[0] - codes[0].mean(0)).abs().amax(0)
    expected = floored_spans(spans, CODE_SPAN_FLOOR) if floored_wins else spans
    torch.testing.assert_close(closure.scale, expected)
    assert len(calls) == 1 + 2 * len(closure_choice.CLOSURE_REGULARIZERS)  # the pure pullback, then 2 scales × 3 λ
    # codes of comparable spans: the floor changes nothing, so each λ is fitted once
    calls.clear()
    codes[..., 1] *= 100.0
    closure_choice.fit_closure(model, datamodule, _FitSpec())
    assert len(calls) == 1 + len(closure_choice.CLOSURE_REGULARIZERS)
