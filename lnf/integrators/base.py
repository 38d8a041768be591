"""Time integration of reduced dynamics: common interface, trajectory container, divergence handling."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional, Protocol

import torch
from torch import Tensor
from lnf.utils import require


class Dynamics(Protocol):
    def acceleration(self, q: Tensor, v: Tensor, t: float = 0.0) -> Tensor: ...


class RolloutDivergedError(RuntimeError):
    """A rollout produced non-finite or exploding states; says where."""

    def __init__(self, step: int, time: float, trajectories: list[int], integrator: str, dt: float,
                 cause: Optional[str] = None, diagnosis: Optional[str] = None) -> None:
        """`cause`: what is non-finite at the initial state already (:func:`initial_state_cause`); `diagnosis`: why
        a rollout that started finite ran away (:func:`divergence_diagnosis`)."""
        self.step, self.time, self.trajectories, self.cause = step, time, trajectories, cause
        where = (f"rollout diverged with {integrator} (dt={dt:g}) at step {step}, t={time:.6g}, "
                 f"trajectories {trajectories[:10]}{' …' if len(trajectories) > 10 else ''}")
        super().__init__(
            f"{where}: {cause}. {NOT_A_STEP_SIZE_PROBLEM}" if cause else
            f"{where}: state became non-finite or exceeded the bound; {diagnosis}." if diagnosis else
            f"{where}: state became non-finite or exceeded the bound. Try a smaller dt (or integrator.substeps), "
            "another integrator, or check the model."
        )


NOT_A_STEP_SIZE_PROBLEM = ("This is not a step-size problem (a smaller dt or more substeps will not help): check the "
                           "scene's potential and mass density at these states (lnf.scenes.check.check_scene) and the "
                           "initial states")


def initial_state_cause(dynamics: Dynamics, q0: Tensor, v0: Tensor, rows: list[int], t0: float = 0.0
                        ) -> Optional[str]:
    """Why trajectories `rows` cannot start, where the cause is at their initial state already: the state (q̃0, q̃̇0)
    or the dynamics' acceleration there is non-finite (a scene's potential or mass that is NaN there, say); None
    where both are finite (the rollout diverged on the way, which a smaller step may cure)."""
    q, v = q0[rows], v0[rows]
    if not bool(torch.isfinite(q).all() and torch.isfinite(v).all()):
        return "the initial state (q̃0, q̃̇0) is already non-finite"
    try:  # the whole batch: per-trajectory controls of a forced scene have its shape
        acc = dynamics.acceleration(q0, v0, t0)
    except Exception:  # noqa: BLE001 - a diagnosis only: the divergence is reported either way
        return None
    if not bool(torch.isfinite(acc[rows]).all()):
        return ("the acceleration is already non-finite at the initial state (the pulled-back potential or mass, from "
                "the scene's potential and mass density, or the model, is NaN or inf there)")
    return None


def central_jacobian(f: "Callable[[Tensor], Tensor]", x: Tensor, steps: Tensor) -> Tensor:
    """∂f/∂x (B, m, n) of a row-wise function f: (B, n) → (B, m) at x (B, n), by central differences with the step
    steps[:, k] (B, n) along x_k: 2n evaluations of f."""
    columns = []
    for k in range(x.shape[-1]):
        dx = torch.zeros_like(x)
        dx[:, k] = steps[:, k]
        columns.append((f(x + dx) - f(x - dx)) / (2 * steps[:, k:k + 1]))
    return torch.stack(columns, -1)


def difference_steps(q: Tensor) -> Tensor:
    """The central-difference step along each coordinate of q (B, d): √(machine ε) · (1 + |q|), in q's dtype."""
    return torch.finfo(q.dtype).eps ** 0.5 * (1.0 + q.abs())


def stiffness_eigenvalues(dynamics: Dynamics, q: Tensor, v: Tensor, t: float = 0.0) -> Tensor:
    """Eigenvalues λ (B, d) complex128 of ∂q̃̈/∂q̃ at (q, v) (B, d) (central differences, 2d evaluations of the
    acceleration); NaN rows where it is not finite. λ ≈ −ω² for an oscillation of frequency ω [rad/s], λ > 0
    for a direction that grows (a concave potential)."""
    q, v = q.detach(), v.detach()
    jac = central_jacobian(lambda x: dynamics.acceleration(x, v, t), q, difference_steps(q)).to(torch.float64)
    finite = torch.isfinite(jac).all(-1).all(-1)
    eig = torch.linalg.eigvals(torch.where(finite[:, None, None], jac, torch.zeros_like(jac)))
    return torch.where(finite[:, None], eig, torch.full_like(eig, float("nan")))


#: above this many coordinates (a nodal full-order model: thousands) :func:`fastest_frequency` estimates the
#: largest |λ| by power iteration instead of a dense Jacobian and its eigenvalues (2d evaluations and O(d³) each)
DENSE_STIFFNESS_MAX_DIM, POWER_ITERATIONS = 64, 60


def fastest_frequency(dynamics: Dynamics, q: Tensor, v: Tensor, t: float = 0.0) -> Tensor:
    """ω_max (B,) [rad/s]: √(max |λ|) over the eigenvalues of ∂q̃̈/∂q̃ at (q, v) (:func:`stiffness_eigenvalues`),
    the fastest reduced time scale there; NaN where the acceleration is not finite. Above
    :data:`DENSE_STIFFNESS_MAX_DIM` coordinates: :data:`POWER_ITERATIONS` steps of the power iteration on
    central-difference Jacobian-vector products (two evaluations each), which approaches max |λ| from below (within
    a few per cent where the top of the spectrum is clustered)."""
    if q.shape[-1] <= DENSE_STIFFNESS_MAX_DIM:
        return stiffness_eigenvalues(dynamics, q, v, t).abs().amax(-1).sqrt()
    q, v = q.detach(), v.detach()
    scale = torch.finfo(q.dtype).eps ** 0.5 * (1.0 + q.abs().amax(-1, keepdim=True))  # (B, 1)
    x = torch.randn(q.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x = x / x.norm(dim=-1, keepdim=True)
    lam = torch.zeros(q.shape[0], dtype=torch.float64)
    for _ in range(POWER_ITERATIONS):
        dx = (scale * x).to(q.dtype)
        jx = ((dynamics.acceleration(q + dx, v, t) - dynamics.acceleration(q - dx, v, t)) / (2 * scale)).double()
        lam = jx.norm(dim=-1)
        x = jx / lam.clamp_min(1e-300)[:, None]
    return torch.where(torch.isfinite(lam), lam, torch.full_like(lam, float("nan"))).sqrt()


#: the most codes :func:`box_frequency` reads the stiffness at (a grid over a table's box)
BOX_FREQUENCY_POINTS = 1024


def box_frequency(dynamics: Dynamics, q: Tensor, v: Tensor, t: float = 0.0) -> float:
    """ω_max [rad/s] over a grid of the box of codes the dynamics are tabulated on (``dynamics.low``/``high``,
    :class:`lnf.tabulated.TabulatedDynamics`; 0 for dynamics without one), at rest. A rollout may swing into any part
    of the box, and a pulled-back potential can stiffen there many times over (a wall past the training codes); the
    step must resolve the stiffest part it can reach, not the part it starts in. The grid is one batch; with a forced
    scene's loads (``dynamics.controls``, one row per trajectory of the rollout's states (q, v) (B, d)) it is read
    in batches of B."""
    low, high = getattr(dynamics, "low", None), getattr(dynamics, "high", None)
    if low is None or high is None:
        return 0.0
    d = len(low)
    per_axis = max(2, min(129, int(BOX_FREQUENCY_POINTS ** (1.0 / d))))
    # the grid stands two difference steps inside the box, so that the stencil of stiffness_eigenvalues stays in it:
    # at the edges some of its evaluations left the box, and a table reads those from the exact pullback, a jet each
    # (at d = 4: 1 000 of the grid's 5 000 rows)
    ends = torch.tensor([list(low), list(high)], dtype=q.dtype, device=q.device)  # (2, d)
    inset = 2.0 * difference_steps(ends)
    ends = torch.where(ends[1] - ends[0] > inset.sum(0), ends + inset * torch.tensor([[1.0], [-1.0]]).to(ends),
                       ends.mean(0).expand_as(ends))
    axes = [torch.linspace(float(a), float(b), per_axis, dtype=q.dtype, device=q.device) for a, b in ends.T.tolist()]
    grid = torch.cartesian_prod(*axes).reshape(-1, d)
    if getattr(dynamics, "controls", None) is None:
        batches = [grid]
    else:  # the loads have the rollout's batch shape: the last batch padded with its own first code
        B = q.shape[0]
        batches = [torch.cat([grid[i:i + B], grid[i:i + 1].expand(max(0, i + B - len(grid)), d)])
                   for i in range(0, len(grid), B)]
    omega = 0.0
    for rows in batches:
        w = fastest_frequency(dynamics, rows, torch.zeros_like(rows), t)
        omega = max(omega, float(torch.nan_to_num(w, nan=0.0).max()))
    return omega


def divergence_diagnosis(dynamics: Dynamics, q: Tensor, v: Tensor, h: float, t: float, integrator: str,
                         substeps: int = 1, limit: Optional[float] = None, max_substeps: Optional[int] = None) -> str:
    """Why trajectories diverged on the way, read at their last finite state (q, v) (B, d) with steps of `h` [s]
    (`substeps` per dt):
    the step against the fastest reduced frequency (a stiff step, cured by substeps), or a step that resolves it (the
    reduced dynamics itself runs away, which a smaller step will not cure), with M̃'s condition number. `limit`: the
    h·ω_max the integrator takes without trouble (None: 2.8 for rk4, RK4's stability bound, else 1.0);
    `max_substeps`: the automatic substeps' cap the rollout already reached, if it did."""
    try:
        with torch.no_grad():
            if q.shape[-1] > DENSE_STIFFNESS_MAX_DIM:  # a full-order model: no dense eigenproblem, no condition number
                omega = float(torch.nan_to_num(fastest_frequency(dynamics, q, v, t), nan=0.0).max())
                growth, cond = 0.0, float("nan")
            else:
                eig = stiffness_eigenvalues(dynamics, q, v, t)
                omega = float(torch.nan_to_num(eig.abs().amax(-1).sqrt(), nan=0.0).max())
                growth = float(torch.nan_to_num(eig.real.clamp(min=0).amax(-1).sqrt(), nan=0.0).max())
                cond = float(torch.linalg.cond(dynamics.mass_matrix(q).to(torch.float64)).max()) \
                    if hasattr(dynamics, "mass_matrix") else float("nan")
    except Exception:  # noqa: BLE001 - a diagnosis only: the divergence is reported either way
        return "try a smaller dt, integrator.substeps or another integrator"
    hw = abs(h) * omega
    if limit is None:
        limit = 2.8 if integrator == "rk4" else 1.0  # RK4's stability bound; the midpoint solve's easy range
    mass = f", M̃'s condition number {cond:.3g}" if math.isfinite(cond) else ""
    if growth > 0.5 * omega > 0:
        mass += f"; a direction grows at {growth:.4g} 1/s: the pulled-back potential is concave there"
    where = f"at the last finite state the fastest reduced frequency is ω_max = {omega:.4g} rad/s (h·ω_max = {hw:.3g}" \
            f" at step h = {abs(h):.3g} s{mass})"
    if hw > limit:
        need = math.ceil(substeps * hw / limit * (1 - 1e-6))  # ω from finite differences: ~1e-8 off
        capped = (f" (the automatic substeps stopped at integrator.max_substeps = {max_substeps}: raise it)"
                  if max_substeps is not None and need > max_substeps else "")
        return (f"{where}: the step is stiff against it{capped}. Take integrator.substeps ≥ {need} "
                f"(h·ω_max ≤ {limit:g})"
                + (" or integrator=implicit_midpoint (A-stable, Newton's method for stiff steps)" if integrator == "rk4"
                   else " or keep integrator.newton=true"))
    return (f"{where}: the step resolves it, so the step size is not the cause. The reduced dynamics itself runs away "
            "from this state (a pulled-back mass M̃ that degenerates, or a potential unbounded below, e.g. off the "
            "range of codes the embedding was trained on): compare the projection floor (projection_rel_l2) with the "
            "rollout error, and check the scene with lnf.scenes.check.check_scene")


@dataclass
class Trajectory:
    """Recorded states: times (T,), q and v (B, T, d); diverged_step (B,) is −1 where the run stayed finite.

    Trajectories that diverged (only kept with ``on_divergence='mark'``) hold NaN from that step on.
    """

    times: Tensor
    q: Tensor
    v: Tensor
    diverged_step: Tensor
    steps: int = 0
    dt: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def diverged(self) -> Tensor:
        return self.diverged_step >= 0


class Integrator:
    """Base class. `integrate` rolls out `steps` steps of size `dt`, recording every `record_every`.

    Args:
        substeps: each step of size dt is taken as (at least) `substeps` steps of size dt/substeps.
        max_abs: a state with |q̃| or |q̃̇| above this counts as diverged.
        max_substeps: automatic substeps (fixed-step methods): where a step h is stiff against the fastest reduced
            frequency ω_max (h·ω_max above the method's `stiff_step`), at the initial states or at a step where a
            trajectory diverged, the rollout takes more substeps, up to `max_substeps`, and retries that step
            (default 64; 1, or any value ≤ `substeps`: fixed substeps).
    """

    name = "integrator"
    stiff_step = 1.0  # the h·ω_max a method takes without trouble (its stability bound, or its solve's easy range)
    stiffness_check_every = 20  # steps between two reads of the fastest frequency (automatic substeps)

    def __init__(self, substeps: int = 1, max_abs: float = 1e6, max_substeps: int = 64) -> None:
        require("integrator.substeps", substeps)
        if not (isinstance(max_abs, (int, float)) and max_abs > 0):  # inf: no bound, only non-finite states diverge
            raise ValueError(f"integrator.max_abs must be a number > 0, got {max_abs!r}")
        require("integrator.max_substeps", max_substeps)
        self.substeps = int(substeps)
        self.max_substeps = max(int(max_substeps), self.substeps)
        self.max_abs = float(max_abs)

    def __repr__(self) -> str:
        auto = f", max_substeps={self.max_substeps}" if self.max_substeps > self.substeps else ""
        return f"{type(self).__name__}(substeps={self.substeps}{auto})"

    def substeps_for(self, dynamics: Dynamics, q: Tensor, v: Tensor, dt: float, t: float, at_least: int,
                     rows: Optional[Tensor] = None) -> int:
        """The substeps (≥ `at_least`, ≤ max_substeps) that bring h·ω_max to the method's `stiff_step` at the states
        (q, v) (B, d) (of `rows` (B,) bool, None: all), ω_max the fastest reduced frequency there
        (:func:`fastest_frequency`, on the whole batch: a forced scene's controls have its shape; 2d evaluations of
        the acceleration); `at_least` where it cannot be read (a non-finite acceleration, dynamics that raise)."""
        if self.max_substeps <= at_least or (rows is not None and not bool(rows.any())):
            return at_least
        try:
            omega = fastest_frequency(dynamics, q, v, t)
            omega = float(torch.nan_to_num(omega if rows is None else omega[rows], nan=0.0).max())
            if rows is None:  # the start of a rollout: also the stiffest part of a table's box it may reach
                omega = max(omega, box_frequency(dynamics, q, v, t))
        except Exception:  # noqa: BLE001 - no frequency, no automatic substeps: the rollout reports what happens
            return at_least
        need = math.ceil(abs(dt) * omega / self.stiff_step * (1 - 1e-6))  # ω from finite differences: ~1e-8 off
        return int(min(self.max_substeps, max(at_least, need)))

    def integrate(self, dynamics: Dynamics, q0: Tensor, v0: Tensor, dt: float, steps: int,
                  record_every: int = 1, t0: float = 0.0, on_divergence: str = "raise",
                  progress: Optional[Callable[[int], None]] = None) -> Trajectory:
        """`steps` steps of `dt` from (q0, v0) (B, d); `progress(k)`, if given, is told of every k steps done."""
        raise NotImplementedError

    # -- shared helpers ---------------------------------------------------------------------------
    @staticmethod
    def _check_args(q0: Tensor, v0: Tensor, dt: float, steps: int, record_every: int, on_divergence: str) -> None:
        if q0.ndim != 2 or q0.shape != v0.shape:
            raise ValueError(f"q0 and v0 must both have shape (B, d), got {tuple(q0.shape)} and {tuple(v0.shape)}")
        if not (dt > 0 and torch.isfinite(torch.tensor(float(dt)))):
            raise ValueError(f"dt must be a positive finite number, got {dt!r}")
        if int(steps) != steps or steps < 0:
            raise ValueError(f"steps must be an integer ≥ 0, got {steps!r}")
        if int(record_every) != record_every or record_every < 1:
            raise ValueError(f"record_every must be an integer ≥ 1, got {record_every!r}")
        if on_divergence not in ("raise", "mark"):
            raise ValueError(f"on_divergence must be 'raise' or 'mark', got {on_divergence!r}")

    def _bad(self, *xs: Tensor) -> Tensor:
        """(B,) mask of trajectories whose state is non-finite or beyond max_abs."""
        bad = torch.zeros(xs[0].shape[0], dtype=torch.bool, device=xs[0].device)
        for x in xs:
            bad |= ~torch.isfinite(x).all(-1) | (x.abs() > self.max_abs).any(-1)
        return bad


class FixedStepIntegrator(Integrator):
    """One-step method on (q̃, q̃̇) (or on an internal state, see `_to_internal`)."""

    def step(self, dynamics: Dynamics, state: tuple[Tensor, ...], h: float, t: float) -> tuple[Tensor, ...]:
        raise NotImplementedError

    def _to_internal(self, dynamics: Dynamics, q: Tensor, v: Tensor) -> tuple[Tensor, ...]:
        return (q, v)

    def _to_qv(self, dynamics: Dynamics, state: tuple[Tensor, ...]) -> tuple[Tensor, Tensor]:
        return state[0], state[1]

    @torch.no_grad()
    def integrate(self, dynamics: Dynamics, q0: Tensor, v0: Tensor, dt: float, steps: int,
                  record_every: int = 1, t0: float = 0.0, on_divergence: str = "raise",
                  progress: Optional[Callable[[int], None]] = None) -> Trajectory:
        self._check_args(q0, v0, dt, steps, record_every, on_divergence)
        B = q0.shape[0]
        substeps = initial = self.substeps_for(dynamics, q0, v0, dt, t0, self.substeps)
        auto = self.max_substeps > self.substeps
        n_rec = steps // record_every + 1
        qs = q0.new_full((B, n_rec, q0.shape[1]), float("nan"))
        vs = torch.full_like(qs, float("nan"))
        qs[:, 0], vs[:, 0] = q0, v0
        diverged = torch.full((B,), -1, dtype=torch.long, device=q0.device)
        alive = torch.ones(B, dtype=torch.bool, device=q0.device)
        state = self._to_internal(dynamics, q0, v0)
        t = t0
        causes: dict[int, str] = {}  # trajectory → why it diverged on the way (divergence_diagnosis)
        raised: list[int] = []  # steps at which the automatic substeps went up
        # the last state whose step was checked against the fastest frequency: a stiff step that blows up later is
        # retaken from there (the states in between may be wrong without being non-finite yet)
        mark = (1, state, alive.clone(), diverged.clone())
        frozen: Optional[tuple[Tensor, ...]] = None  # the internal state dead trajectories are held at
        n, done = 1, 0
        while n <= steps:
            if auto and n > 1 and (n - 1) % self.stiffness_check_every == 0 and substeps < self.max_substeps:
                q_now, v_now = self._to_qv(dynamics, state)
                substeps = self._raise(dynamics, q_now, v_now, alive, dt, t0 + (n - 1) * dt, substeps, n, raised)
                mark = (n, state, alive.clone(), diverged.clone())
            before = state
            state = self._advance(dynamics, before, dt, substeps, t0 + (n - 1) * dt)
            t = t0 + n * dt
            bad = self._bad(*state) & alive
            if bad.any() and auto and substeps < self.max_substeps:  # a stiff step? retake it from the mark
                q_last, v_last = self._to_qv(dynamics, before)
                more = self._raise(dynamics, q_last, v_last, bad, dt, t - dt, substeps, n, raised)
                if more > substeps:
                    substeps = more
                    n, state, alive, diverged = mark[0], mark[1], mark[2].clone(), mark[3].clone()
                    causes = {i: c for i, c in causes.items() if not bool(alive[i])}
                    continue
            if bad.any():
                rows = bad.nonzero().flatten().tolist()
                cause = initial_state_cause(dynamics, q0, v0, rows, t0) if n == 1 else None
                diagnosis = None
                if cause is None:
                    q_last, v_last = self._to_qv(dynamics, before)
                    diagnosis = divergence_diagnosis(dynamics, q_last[rows], v_last[rows], dt / substeps, t - dt,
                                                     self.name, substeps, self.stiff_step,
                                                     self.max_substeps if auto else None)
                    causes.update(dict.fromkeys(rows, diagnosis))
                if on_divergence == "raise":
                    raise RolloutDivergedError(n, t, rows, self.name, dt, cause, diagnosis)
                diverged[bad] = n
                alive &= ~bad
                if not alive.any():
                    break
                frozen = self._to_internal(dynamics, q0, v0) if frozen is None else frozen
            if frozen is not None:  # dead trajectories held at a harmless state, at every step: a NaN row poisons
                # batched solves (it fails every fixed-point iteration and sends the midpoint rule to Newton's method)
                state = tuple(torch.where(alive[:, None], s, s0) for s, s0 in zip(state, frozen))
            if progress is not None and n > done:
                progress(1)
            done = max(done, n)
            if n % record_every == 0:
                q, v = self._to_qv(dynamics, state)
                r = n // record_every
                qs[:, r] = torch.where(alive[:, None], q, float("nan"))
                vs[:, r] = torch.where(alive[:, None], v, float("nan"))
            n += 1
        times = t0 + dt * record_every * torch.arange(n_rec, dtype=torch.float64)
        extra: dict = {"divergence_causes": causes} if causes else {}
        if substeps > self.substeps:
            extra["substeps"] = {"initial": initial, "final": substeps, "raised_at_steps": raised}
        return Trajectory(times=times, q=qs, v=vs, diverged_step=diverged, steps=steps, dt=dt, extra=extra)

    def _raise(self, dynamics: Dynamics, q: Tensor, v: Tensor, rows: Tensor, dt: float, t: float, substeps: int,
               n: int, raised: list[int]) -> int:
        """The automatic substeps for the states (q, v) of `rows` at step n (never fewer than `substeps`); n noted
        in `raised` where they go up."""
        more = self.substeps_for(dynamics, q, v, dt, t, substeps, rows)
        if more > substeps:
            raised.append(n)
            self._substeps_raised()
        return more

    def _substeps_raised(self) -> None:
        """Told when the automatic substeps go up (a method may drop what it learnt about the stiffer step)."""

    def _advance(self, dynamics: Dynamics, state: tuple[Tensor, ...], dt: float, substeps: int, t: float
                 ) -> tuple[Tensor, ...]:
        """One step dt from `state` at time t, as `substeps` steps of dt / substeps."""
        h = dt / substeps
        for k in range(substeps):
            state = self.step(dynamics, state, h, t + k * h)
        return state
