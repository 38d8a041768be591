"""Orders of accuracy and energy behaviour on the analytic pendulum."""
import math

import numpy as np
import pytest
import torch

from analytic import LinearModeEmbedding
from lnf.dynamics import ReducedDynamics
from lnf.integrators import Dopri5, ImplicitMidpoint, RK4, RolloutDivergedError, get_integrator
from lnf.quadrature import gauss_legendre_rule


@pytest.fixture
def dyn(pendulum):
    quad = gauss_legendre_rule(6, pendulum.bounds).to(torch.float64)
    return ReducedDynamics(LinearModeEmbedding(pendulum).jet, pendulum, quad)


STATE = np.array([[1.0, 0.5]])


def _final_error(dyn, pendulum, integrator, dt, horizon=1.0):
    steps = int(round(horizon / dt))
    ref = pendulum.simulate(STATE, np.array([0.0, horizon]))[:, -1]
    traj = integrator.integrate(dyn, torch.tensor(STATE[:, :1]), torch.tensor(STATE[:, 1:]), dt, steps,
                                record_every=steps)
    return abs(float(traj.q[0, -1, 0]) - ref[0, 0])


@pytest.mark.parametrize("integrator,order", [(RK4(), 4), (ImplicitMidpoint(order=2), 2),
                                              (ImplicitMidpoint(order=4), 4)])
def test_order_of_accuracy(dyn, pendulum, integrator, order):
    e1 = _final_error(dyn, pendulum, integrator, 0.1)
    e2 = _final_error(dyn, pendulum, integrator, 0.05)
    assert np.log2(e1 / e2) == pytest.approx(order, abs=0.35)


def test_dopri5_meets_tolerance(dyn, pendulum):
    assert _final_error(dyn, pendulum, Dopri5(rtol=1e-10, atol=1e-10), 0.05) < 1e-8


def _energy_drift(dyn, integrator, dt, steps):
    q0, v0 = torch.tensor(STATE[:, :1]), torch.tensor(STATE[:, 1:])
    traj = integrator.integrate(dyn, q0, v0, dt, steps, record_every=10)
    T, V = dyn.energies(traj.q, traj.v)
    E = (T + V)[0]
    return (E - E[0]).abs() / 9.81


def test_midpoint_energy_bounded_rk4_drifts(dyn):
    """Long run at a coarse step: midpoint's energy error stays bounded, RK4's grows with time."""
    steps, dt = 1000, 0.2
    mid = _energy_drift(dyn, ImplicitMidpoint(order=2), dt, steps)
    rk4 = _energy_drift(dyn, RK4(), dt, steps)
    n = len(mid) // 4
    assert mid[-n:].max() < 1.5 * mid[:n].max()  # bounded: no growth from first to last quarter
    assert rk4[-n:].max() > 2 * rk4[:n].max()  # drifts (RK4 is dissipative on the pendulum)
    assert mid.max() < 0.1 * rk4.max()


def test_divergence_is_reported_with_step_and_time(dyn):
    q0 = torch.tensor([[1.0]], dtype=torch.float64)
    v0 = torch.tensor([[1e5]], dtype=torch.float64)
    with pytest.raises(RolloutDivergedError, match=r"step \d+, t="):
        RK4(max_abs=1e6).integrate(dyn, q0, v0, 0.5, 100)
    traj = RK4(max_abs=1e6).integrate(dyn, torch.tensor([[1.0], [0.1]], dtype=torch.float64),
                                      torch.tensor([[1e5], [0.0]], dtype=torch.float64), 0.5, 100, on_divergence="mark")
    assert traj.diverged.tolist() == [True, False]
    assert torch.isnan(traj.q[0, -1]).all() and torch.isfinite(traj.q[1]).all()


def test_get_integrator_rejects_unknown_names():
    with pytest.raises(ValueError, match="unknown integrator 'euler'"):
        get_integrator("euler")
    assert isinstance(get_integrator({"name": "rk4", "substeps": 2}), RK4)
    with pytest.raises(ValueError, match="substeps"):
        RK4(substeps=0)
    with pytest.raises(ValueError, match="order"):
        ImplicitMidpoint(order=3)


def test_newton_solves_midpoint_steps_the_fixed_point_iteration_cannot(dyn):
    """At dt = 0.5 the order-4 composition's −1.7·dt substep defeats the fixed-point iteration; Newton does not."""
    q0 = torch.tensor([[1.2], [0.3]], dtype=torch.float64)
    v0 = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    plain = ImplicitMidpoint(order=4, newton=False).integrate(dyn, q0, v0, 0.5, 40, on_divergence="mark")
    assert plain.diverged.any()
    solver = ImplicitMidpoint(order=4, newton=True)
    traj = solver.integrate(dyn, q0, v0, 0.5, 40, on_divergence="mark")
    assert not traj.diverged.any() and solver.newton_solves > 0
    T, V = dyn.energies(traj.q, traj.v)
    energy = (T + V).numpy()
    assert np.abs(energy - energy[:, :1]).max() < 0.05 * energy[:, 0].max()  # bounded, not drifting


def test_the_default_midpoint_carries_a_stiff_step_and_stops_wasting_fixed_point_iterations(dyn):
    """By default (newton=True) a step the fixed-point iteration cannot take, or would take slowly, goes to Newton's
    method within 10 iterations; once a rollout has needed it, later solves try 3 fixed-point iterations before
    Newton instead of max_iter = 50."""
    q0 = torch.tensor([[1.2], [0.3]], dtype=torch.float64)
    v0 = torch.tensor([[0.0], [1.0]], dtype=torch.float64)
    solver = ImplicitMidpoint(order=4, max_substeps=1)  # fixed substeps: the stiff step itself goes to Newton
    assert solver.newton
    traj = solver.integrate(dyn, q0, v0, 0.5, 40, on_divergence="mark")
    assert not traj.diverged.any() and solver.newton_solves > 0
    assert max(solver.iterations) <= 10 and sum(n > 3 for n in solver.iterations) <= 1  # only the first solve
    # a rollout whose fixed-point iteration converges fast keeps it (the same numbers as newton=False): float32, where
    # the tolerance is 16 ε; in float64 (tolerance 1e-12) it contracts at ~0.3 for ~12 iterations a solve, so Newton's
    # method takes over from its third, to the same solution within the tolerance
    dyn32 = ReducedDynamics(dyn.jet, dyn.scene, gauss_legendre_rule(6, dyn.scene.bounds).to(torch.float32))
    easy = [ImplicitMidpoint(order=4, newton=flag).integrate(dyn32, q0.float(), v0.float(), 0.05, 40)
            for flag in (True, False)]
    assert torch.equal(easy[0].q, easy[1].q) and torch.equal(easy[0].v, easy[1].v)
    solvers = [ImplicitMidpoint(order=4, newton=flag) for flag in (True, False)]
    slow = [solver.integrate(dyn, q0, v0, 0.05, 40) for solver in solvers]
    assert solvers[0].newton_solves > 0 and max(solvers[0].iterations) <= 3 < max(solvers[1].iterations)
    torch.testing.assert_close(slow[0].q, slow[1].q, rtol=0, atol=1e-9)


def test_newton_reuses_its_jacobian_while_the_iteration_contracts():
    """A stiff linear spring (h·ω = 20, fixed substeps): every step goes to Newton's method, whose Jacobian is
    computed once and reused by all later solves (it is constant here), at a few evaluations per solve; the
    result is the exact midpoint map (a rotation by 2·atan(hω/2) in (q, p/ω))."""
    omega, dt, steps = 400.0, 0.05, 30
    calls = []

    class Counted(_SpringHamiltonian):
        def hamiltonian_derivatives(self, q, p, t=0.0):
            calls.append(q.shape[0])
            return super().hamiltonian_derivatives(q, p, t)

    q0 = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    v0 = torch.tensor([[0.0, 200.0]], dtype=torch.float64)
    solver = ImplicitMidpoint(order=2, max_substeps=1)
    traj = solver.integrate(Counted(omega), q0, v0, dt, steps)
    assert not traj.diverged.any()
    assert solver.jacobians == 1 and solver.newton_solves >= steps - 3
    assert len(calls) / steps < 10  # 3 fixed-point tries and ~2 chord iterations per solve, not 4d per iteration
    theta = 2 * np.arctan(dt * omega / 2) * np.arange(steps + 1)
    z0 = q0.numpy()[0] + 1j * v0.numpy()[0] / omega  # q + i p/ω turns by −θ per step
    exact = z0[None, :] * np.exp(-1j * theta)[:, None]
    assert np.allclose(traj.q[0].numpy(), exact.real, atol=1e-9)


def test_a_trajectory_marked_diverged_costs_the_later_steps_no_newton_solve():
    """A row whose force turns NaN (a closure's guard during the shooting) is marked diverged and frozen: the later
    steps' batched solves see a finite state there, not NaN, which fails every fixed-point iteration and sent the row
    to Newton's method (a fresh Jacobian, 4d evaluations each) at every step to the end of the rollout."""

    class Cliff(_SpringHamiltonian):  # a soft spring whose force is NaN past q = 1.5 (the first coordinate)
        def hamiltonian_derivatives(self, q, p, t=0.0):
            v, force = super().hamiltonian_derivatives(q, p, t)
            return v, torch.where((q[:, :1] > 1.5), torch.full_like(force, float("nan")), force)

    q0 = torch.tensor([[1.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
    v0 = torch.tensor([[0.0, 0.0], [3.0, 0.0]], dtype=torch.float64)  # the second row runs past the cliff
    solver = ImplicitMidpoint(order=2, max_substeps=1)
    traj = solver.integrate(Cliff(1.0), q0, v0, 0.05, 200, on_divergence="mark")
    assert traj.diverged_step[0] == -1 and 0 < int(traj.diverged_step[1]) < 20
    assert solver.newton_solves <= 2 and solver.jacobians <= 2


def test_settings_of_another_integrator_are_a_clear_error():
    """+experiment=<scene> sets integrator.order for the midpoint rule; RK4 must say how to drop it."""
    from lnf.integrators import get_integrator

    with pytest.raises(ValueError, match=r"integrator rk4 takes no integrator.order .* ~integrator.order"):
        get_integrator({"name": "rk4", "order": 2})


@pytest.mark.parametrize("integrator", [RK4(substeps=2), ImplicitMidpoint(order=4), Dopri5()])
def test_progress_hears_of_every_step(dyn, integrator):
    """The progress callback (a progress bar's advance) is told of all `steps`, whatever the integrator."""
    done = []
    q0, v0 = torch.tensor(STATE[:, :1]), torch.tensor(STATE[:, 1:])
    traj = integrator.integrate(dyn, q0, v0, 0.05, 12, record_every=3, progress=done.append)
    assert sum(done) == 12 and traj.q.shape[1] == 5


class _Spring:
    """q̈ = −ω² q (frequency ω [rad/s]) with an identity mass: a stiff step is dt·ω beyond the method's range."""

    def __init__(self, omega: float) -> None:
        self.omega = omega

    def acceleration(self, q, v, t=0.0):
        return -self.omega ** 2 * q

    def mass_matrix(self, q):
        return torch.eye(q.shape[-1], dtype=q.dtype).expand(q.shape[0], -1, -1)


class _SpringHamiltonian(_Spring):
    """The same spring with the Hamiltonian interface of the implicit midpoint rule (unit mass: p̃ = q̃̇)."""

    def momentum(self, q, v):
        return v

    def velocity(self, q, p):
        return p

    def hamiltonian_derivatives(self, q, p, t=0.0):
        return p, self.acceleration(q, p, t)


class _Runaway:
    """q̈ = 50 q³: escapes in finite time whatever the step (a potential unbounded below)."""

    def acceleration(self, q, v, t=0.0):
        return 50 * q ** 3


def test_divergence_message_names_a_stiff_step_and_the_substeps_that_cure_it():
    from lnf.integrators.base import fastest_frequency

    q0, v0 = torch.ones(2, 1, dtype=torch.float64), torch.zeros(2, 1, dtype=torch.float64)
    assert torch.allclose(fastest_frequency(_Spring(40.0), q0, v0), torch.full((2,), 40.0, dtype=torch.float64))
    with pytest.raises(RolloutDivergedError, match=r"ω_max = 200 rad/s \(h·ω_max = 10 .*stiff.*substeps ≥ 5"):
        RK4(max_substeps=1).integrate(_Spring(200.0), q0, v0, 0.05, 100)
    RK4(substeps=5, max_substeps=1).integrate(_Spring(200.0), q0, v0, 0.05, 100)  # the advice works
    marked = RK4(max_substeps=1).integrate(_Spring(200.0), q0, v0, 0.05, 100, on_divergence="mark")
    assert set(marked.extra["divergence_causes"]) == {0, 1}
    with pytest.raises(RolloutDivergedError, match=r"max_substeps = 3: raise it.*substeps ≥ 5"):
        RK4(max_substeps=3).integrate(_Spring(200.0), q0, v0, 0.05, 100)  # the cap of the automatic substeps
    with pytest.raises(RolloutDivergedError, match=r"grows at .* 1/s.*step size is not the cause"):
        RK4().integrate(_Runaway(), q0, v0, 0.001, 10000)


class _Stiffening:
    """q̈ = −ω(t)² q with ω = 10 rad/s until t = 0.52 s, 400 rad/s after: a step fine at the start turns stiff
    between two reads of the fastest frequency."""

    def acceleration(self, q, v, t=0.0):
        return -(10.0 if t < 0.52 else 400.0) ** 2 * q


@pytest.mark.parametrize("cls", [RK4, ImplicitMidpoint])
def test_automatic_substeps_carry_a_stiff_step_by_default(cls):
    """By default a step stiff against the fastest reduced frequency is taken in ⌈h·ω_max / stiff_step⌉ substeps
    (read at the initial states), and the rollout is the one fixed substeps give; with them off it is not."""
    q0, v0 = torch.ones(2, 1, dtype=torch.float64), torch.zeros(2, 1, dtype=torch.float64)
    spring = _Spring(200.0) if cls is RK4 else _SpringHamiltonian(200.0)
    need = math.ceil(0.05 * 200.0 / cls.stiff_step)
    auto = cls().integrate(spring, q0, v0, 0.05, 40)
    fixed = cls(substeps=need, max_substeps=1).integrate(spring, q0, v0, 0.05, 40)
    assert auto.extra["substeps"] == {"initial": need, "final": need, "raised_at_steps": []}
    assert torch.equal(auto.q, fixed.q) and not auto.diverged.any()
    assert bool(auto.q.abs().max() <= 1.0 + 1e-6)  # both keep a linear spring within its amplitude at h·ω ≤ 2
    if cls is RK4:  # RK4 without them runs away; the midpoint rule stays bounded (A-stable) but out of phase
        assert RK4(max_substeps=1).integrate(spring, q0, v0, 0.05, 40, on_divergence="mark").diverged.all()


def test_automatic_substeps_rise_where_a_rollout_turns_stiff_and_retake_that_step():
    q0, v0 = torch.ones(1, 1, dtype=torch.float64), torch.zeros(1, 1, dtype=torch.float64)
    traj = RK4().integrate(_Stiffening(), q0, v0, 0.05, 60)
    assert not traj.diverged.any() and traj.extra["substeps"]["initial"] == 1
    assert traj.extra["substeps"]["final"] == 10 and traj.extra["substeps"]["raised_at_steps"]
    assert min(traj.extra["substeps"]["raised_at_steps"]) > 10  # where it blew up, after t = 0.52 s
    # retaken from the last checked state (t = 0), not from the blown-up one: RK4 at h·ω ≤ 2 keeps |q| ≤ 1
    assert bool(traj.q.abs().max() <= 1.0 + 1e-6)
    fixed = RK4(substeps=10, max_substeps=1).integrate(_Stiffening(), q0, v0, 0.05, 60)
    assert torch.equal(traj.q, fixed.q)
class _Walled:
    """q̈ = −k(q) q on a table's box [−2, 2]: ω = 2 rad/s near the start, 60 rad/s past |q| = 1.2 (a pulled-back
    potential that stiffens into a wall past the training codes)."""

    low, high = [-2.0], [2.0]

    def acceleration(self, q, v, t=0.0):
        return -(4.0 + 3596.0 * torch.sigmoid((q.abs() - 1.2) * 40.0)) * q


def test_the_first_substeps_resolve_the_stiffest_part_of_a_tables_box_not_only_the_start():
    """A rollout that starts where the potential is soft may swing into its wall: the substeps read at the start
    cover the stiffest frequency on the box (a grid of it), where the dynamics are tabulated on one."""
    q0, v0 = torch.full((3, 1), 0.3, dtype=torch.float64), torch.zeros(3, 1, dtype=torch.float64)
    walled = _Walled()
    traj = RK4().integrate(walled, q0, v0, 0.1, 10)
    x = torch.linspace(-2.0, 2.0, 4001, dtype=torch.float64)[:, None].requires_grad_(True)
    slope = torch.autograd.grad(walled.acceleration(x, None).sum(), x)[0]  # ∂q̈/∂q, −ω² (60 rad/s and the wall's rise)
    need = math.ceil(0.1 * float(slope.abs().max().sqrt()) / RK4.stiff_step)
    assert need >= 3 and traj.extra["substeps"]["initial"] in (need - 1, need)  # read on a coarser grid of the box

    class Untabulated:  # no box: the frequency at the start (2 rad/s) decides
        acceleration = walled.acceleration

    assert "substeps" not in RK4().integrate(Untabulated(), q0, v0, 0.1, 10).extra


def test_an_integrator_config_builds_the_class_it_names():
    """conf/integrator/*.yaml give a `_target_`: the class is built from it (not a name guessed from it)."""
    integ = get_integrator({"_target_": "lnf.integrators.ImplicitMidpoint", "order": 2, "substeps": 3})
    assert isinstance(integ, ImplicitMidpoint) and integ.order == 2 and integ.substeps == 3
    with pytest.raises(ValueError, match=r"integrator._target_=lnf.dynamics.ReducedDynamics: not a subclass"):
        get_integrator({"_target_": "lnf.dynamics.ReducedDynamics"})
    with pytest.raises(ValueError, match=r"integrator rk4 takes no integrator.order"):
        get_integrator({"_target_": "lnf.integrators.RK4", "order": 2})


class _Springs:
    """q̈ = −K q for a symmetric positive definite K (d × d): ω_max² is K's largest eigenvalue."""

    def __init__(self, d, seed=0):
        g = torch.Generator().manual_seed(seed)
        a = torch.randn(d, d, generator=g, dtype=torch.float64)
        self.K = a @ a.T / d + torch.eye(d, dtype=torch.float64)

    def acceleration(self, q, v, t=0.0):
        return -q @ self.K


def test_the_fastest_frequency_of_a_full_order_model_comes_from_a_power_iteration_not_a_dense_eigenproblem():
    """Thousands of nodal coordinates: a dense Jacobian (2d evaluations) and its eigenvalues (O(d³) per state) took
    minutes per check on a 64² grid; above DENSE_STIFFNESS_MAX_DIM the power iteration reads max |λ| in 2 × 40
    evaluations, from below and within a few per cent on this clustered spectrum; the divergence diagnosis reads it
    the same way."""
    from lnf.integrators.base import DENSE_STIFFNESS_MAX_DIM, divergence_diagnosis, fastest_frequency

    d = 4 * DENSE_STIFFNESS_MAX_DIM
    springs = _Springs(d)
    exact = float(torch.linalg.eigvalsh(springs.K).max().sqrt())
    q, v = 0.1 * torch.ones(3, d, dtype=torch.float64), torch.zeros(3, d, dtype=torch.float64)
    calls = []
    counted = type("Counted", (), {"acceleration": lambda self, q, v, t=0.0: calls.append(1) or springs.acceleration(q, v)})()
    omega = fastest_frequency(counted, q, v)
    assert omega.shape == (3,) and bool(((omega > 0.95 * exact) & (omega <= exact * (1 + 1e-6))).all()), (omega, exact)
    assert len(calls) < d  # not a column per coordinate
    text = divergence_diagnosis(springs, q, v, h=10 / exact, t=0.0, integrator="rk4")
    assert "ω_max = " in text and "stiff" in text
