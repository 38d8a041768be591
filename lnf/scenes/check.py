"""``check_scene``: one call that checks a scene of your own before you train on it.

It checks the required core (attributes, ω0, V), then each optional part the scene declares
(:meth:`Scene.capabilities`): shapes and broadcasting over leading axes, a positive density, the potential V
on a quadrature rule against the scene's own potential energy, and energy conservation of its simulator
where the scene is conservative. Every problem found is reported with what to fix.

Optional parts are demanded only where a run needs them: ``needs`` names those capabilities (the keys of
:meth:`Scene.capabilities`), e.g. ``field_gradients`` for the gradient loss ``model.gradient_weight > 0``.
``python -m lnf.train`` runs it with the needs of its configuration before it generates data or trains.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping

import numpy as np
import torch

from lnf.quadrature import Quadrature, gauss_legendre_rule
from lnf.scenes.base import Scene


class SceneCheckError(ValueError):
    """A scene failed :func:`check_scene`; the message lists every problem and what to fix."""


#: The methods a scene defines for each capability that :func:`check_scene`'s ``needs`` may name.
CAPABILITY_METHODS: dict[str, tuple[str, ...]] = {
    "simulator": ("simulate", "sample_initial_states"), "fields": ("fields",),
    "true_energies": ("true_energy_parts",), "field_gradients": ("field_gradients",), "clamp": ("clamp_factor",),
    "kinetic_correction": ("kinetic_correction",), "release_at_rest": ("released_at_rest",),
    "damping": ("with_damping",), "element_quadrature": ("element_quadrature",),
    "nodal_quadrature": ("nodal_quadrature",),
}


def _needs(needs: "Iterable[str] | Mapping[str, str]") -> dict[str, str]:
    """`needs` as {capability: what needs it}; an unknown capability is a ValueError naming the known ones."""
    named = dict(needs) if isinstance(needs, Mapping) else {n: "" for n in needs}
    unknown = sorted(set(named) - set(CAPABILITY_METHODS))
    if unknown:
        raise ValueError(f"check_scene(needs=...) got unknown capabilities {unknown}; expected some of "
                         f"{sorted(CAPABILITY_METHODS)}")
    return named


def _missing_needs(scene: Scene, needs: dict[str, str]) -> list[str]:
    """One problem per needed capability whose methods the scene's class does not define."""
    problems = []
    cls = type(scene)
    for cap, why in needs.items():
        missing = [m for m in CAPABILITY_METHODS[cap] if not scene.provides(m)]
        if missing:
            methods = " and ".join(f"{m}()" for m in missing)
            problems.append(f"{cap}: {why or 'this run'} needs {methods}, which {cls.__module__}.{cls.__qualname__} "
                            f"does not define: define {'them' if len(missing) > 1 else 'it'} in the scene's class "
                            f"(shapes and units: docs/own_system.md, lnf.scenes.Scene.{missing[0]})")
    return problems


@dataclass
class SceneReport:
    """What :func:`check_scene` found: `passed` and `problems` (one line each), `skipped` (parts not declared)."""

    scene: str
    passed: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def __str__(self) -> str:
        lines = [f"check_scene({self.scene}): {len(self.passed)} passed, {len(self.problems)} problems"]
        lines += [f"  ok       {p}" for p in self.passed] + [f"  PROBLEM  {p}" for p in self.problems]
        lines += [f"  skipped  {p}" for p in self.skipped]
        return "\n".join(lines)


def _run(report: SceneReport, what: str, check: Callable[[], str | None]) -> bool:
    """Run one check: it returns None (passed) or a problem; an exception is a problem naming it."""
    try:
        problem = check()
    except Exception as err:  # noqa: BLE001 - a failing user method is exactly what is being checked
        problem = f"raised {type(err).__name__}: {err}"
    if problem:
        report.problems.append(f"{what}: {problem}")
        return False
    report.passed.append(what)
    return True


def _core(scene: Scene) -> Callable[[], str | None]:
    def check() -> str | None:
        dim = scene.field_dim
        if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
            return f"field_dim must be an integer ≥ 1, got {dim!r}"
        b = np.asarray(scene.bounds, dtype=float)
        if b.ndim != 2 or b.shape[1] != 2 or not 1 <= b.shape[0] <= 3 or not (b[:, 1] > b[:, 0]).all():
            return f"bounds must be [[lo, hi], ...] with hi > lo, one row for each of 1 to 3 axes, got {scene.bounds!r}"
        scale = scene.energy_scale
        if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
            return f"energy_scale must be a finite number > 0 (the energy errors are divided by), got {scale!r}"
        spec = scene.spec()
        try:
            json.dumps(spec)
        except (TypeError, ValueError) as err:
            return f"params() must return JSON-able values (datasets and checkpoints store them): {err}"
        rebuilt = type(scene)(**scene.params())
        if rebuilt.spec() != spec:
            return f"type(scene)(**scene.params()) gives another scene ({rebuilt.spec()} against {spec})"
        return None
    return check


def _density(scene: Scene, points: torch.Tensor) -> Callable[[], str | None]:
    def check() -> str | None:
        rho = scene.density(points)
        if tuple(rho.shape) != (points.shape[0],):
            return f"density(points (N, dim_B)) must return (N,) = ({points.shape[0]},), got {tuple(rho.shape)}"
        if not bool(torch.isfinite(rho).all()) or not bool((rho > 0).all()):
            return f"density must be finite and > 0 on the body, got values from {float(rho.min()):.3g} to {float(rho.max()):.3g}"
        batched = scene.density(points.expand(3, *points.shape))
        if tuple(batched.shape) != (3, points.shape[0]) or not torch.allclose(batched[1], rho):
            return f"density must broadcast over leading axes: points (3, N, dim_B) gave {tuple(batched.shape)}"
        return None
    return check


def _potential(scene: Scene, quadrature: Any) -> Callable[[], str | None]:
    def check() -> str | None:
        V = scene.potential(quadrature)
        n, A = len(quadrature), scene.field_dim
        gen = torch.Generator().manual_seed(0)
        q = 0.1 * torch.randn(4, n, A, generator=gen, dtype=quadrature.weights.dtype)
        G = 0.1 * torch.randn(4, n, A, scene.body_dim, generator=gen, dtype=q.dtype) if V.needs_gradient else None
        out = V(q, G)
        if tuple(out.shape) != (4,):
            return f"potential(rule)(q (B, N, A){', G' if G is not None else ''}) must return (B,) = (4,), got {tuple(out.shape)}"
        if not bool(torch.isfinite(out).all()):
            return "potential gives non-finite values for small random fields"
        one = V(q[1:2], None if G is None else G[1:2])
        if not torch.allclose(one[0], out[1], rtol=1e-5, atol=1e-8 * scene.energy_scale):
            return "potential of a batch differs from that of each field alone: it must treat the batch axis independently"
        return None
    return check


def _simulated(scene: Scene, n: int, times: np.ndarray) -> tuple[np.ndarray, str | None]:
    initial = np.asarray(scene.sample_initial_states(n, np.random.default_rng(0)), dtype=float)
    if initial.ndim != 2 or initial.shape[0] != n:
        return initial, f"sample_initial_states({n}, rng) must return (n, S), got {initial.shape}"
    states = np.asarray(scene.simulate(initial, times), dtype=float)
    if states.shape != (n, len(times), initial.shape[1]):
        return states, f"simulate(initial (n, S), times (T,)) must return (n, T, S) = {(n, len(times), initial.shape[1])}, got {states.shape}"
    if not np.isfinite(states).all():
        return states, "simulate returned non-finite states"
    return states, None


def _gradients_match_fields(scene: Scene, states: np.ndarray, points: np.ndarray, G: np.ndarray,
                            tolerance: float = 1e-3) -> str | None:
    """None when `G` = field_gradients(states, points) matches central differences of ``fields`` (step 1e-6 of the
    body's box, interior points), else the problem: a wrong ∇_X q would train the gradient loss on the wrong target."""
    h = 1e-6 * max(float(hi) - float(lo) for lo, hi in scene.bounds)
    every = max(1, len(points) // 256)  # one state and ≤ 256 points keep the check cheap on a fine mesh
    states, points, G = states[:1, -1:], points[::every], G[:1, -1:, ::every]
    columns = []
    for j in range(points.shape[1]):
        step = np.zeros(points.shape[1])
        step[j] = h
        ahead, behind = scene.fields(states, points + step)[0], scene.fields(states, points - step)[0]
        columns.append((np.asarray(ahead) - np.asarray(behind)) / (2 * h))
    differences = np.stack(columns, -1)
    gap = float(np.max(np.abs(G - differences))) / max(float(np.max(np.abs(differences))), 1e-12)
    if gap > tolerance:
        return (f"field_gradients differs from central differences of fields by {gap:.3g} of the largest gradient "
                f"(tolerance {tolerance}): it must be ∇_X of the q that fields() returns")
    return None


def check_scene(scene: Scene, raise_on_problem: bool = True, n_trajectories: int = 2, n_times: int = 21,
                dt: float = 0.05, quadrature_order: int = 12, potential_tolerance: float = 0.02,
                energy_tolerance: float = 1e-3, *, needs: "Iterable[str] | Mapping[str, str]" = (),
                simulate: bool = True) -> SceneReport:
    """Check `scene` before training on it; returns the report, or raises :class:`SceneCheckError` listing every
    problem (with ``raise_on_problem``).

    `needs`: the capabilities (keys of :meth:`Scene.capabilities`: ``simulator``, ``fields``, ``true_energies``,
    ``field_gradients``, ``clamp``, ...) that the run needs, optionally as {capability: what needs it}; each one
    the scene does not define is a problem naming its methods. Optional parts not needed are checked where the
    scene defines them, and never demanded: a potential that needs ∇_X q is compared with the reference energies
    only where the scene defines ``field_gradients``. `simulate`: False checks the declarations without running
    the simulator (and leaves out the checks of its states).

    The potential is compared with the scene's own potential energy on `n_trajectories` simulated states, its
    fields sampled on a Gauss–Legendre rule of `quadrature_order` nodes per axis: within `potential_tolerance`
    of ``energy_scale``. A conservative scene's simulator must keep its total energy within `energy_tolerance`
    of ``energy_scale`` over `n_times` samples `dt` [s] apart.
    """
    report = SceneReport(scene=type(scene).__qualname__)
    needed = _needs(needs)
    missing = _missing_needs(scene, needed)
    if not _run(report, "required attributes (field_dim, bounds, energy_scale, params)", _core(scene)):
        report.problems += missing
        return _finish(report, raise_on_problem)
    report.problems += missing
    if needed and not missing:
        report.passed.append(f"the optional parts this run needs ({', '.join(needed)})")
    rule = gauss_legendre_rule(quadrature_order, scene.bounds)
    rule_text = f"a {quadrature_order}-point-per-axis Gauss–Legendre rule"
    if scene.provides("element_quadrature"):  # a body on a mesh: its elements' own rule (exact for its own fields)
        own = scene.element_quadrature()
        rule, rule_text = Quadrature(own.points.to(rule.points), own.weights.to(rule.weights)), "its mesh's element rule"
    _run(report, "density ω0 (shape, broadcasting, > 0)", _density(scene, rule.points))
    potential_ok = _run(report, "potential V on a quadrature rule (shape, batch)", _potential(scene, rule))
    caps = scene.capabilities()
    if not caps["simulator"]:
        report.skipped.append("full-order simulator (simulate, sample_initial_states): not defined; train from "
                              "your own trajectories")
        return _finish(report, raise_on_problem)
    if not simulate:
        report.skipped.append("full-order simulator and the checks of its states: not run (simulate=False)")
        return _finish(report, raise_on_problem)
    times = dt * np.arange(n_times)
    holder: dict[str, np.ndarray] = {}

    def simulator() -> str | None:
        holder["states"], problem = _simulated(scene, n_trajectories, times)
        return problem

    if not _run(report, "full-order simulator (shapes, finite)", simulator):
        return _finish(report, raise_on_problem)
    states = holder["states"]
    points = rule.points.numpy().astype(np.float64)
    if caps["fields"]:
        def fields() -> str | None:
            q, v = scene.fields(states, points)
            want = (*states.shape[:2], len(points), scene.field_dim)
            if np.shape(q) != want or np.shape(v) != want:
                return f"fields(states (n, T, S), points (N, dim_B)) must return q, q̇ of shape {want}, got {np.shape(q)}, {np.shape(v)}"
            q0, _ = scene.fields(states[0, 0], points)
            if np.shape(q0) != want[2:] or not np.allclose(q0, q[0, 0]):
                return "fields must broadcast over the leading axes of states: a single state (S,) gave another field"
            return None
        _run(report, "fields of full-order states (shapes, broadcasting)", fields)
    else:
        report.skipped.append("fields(): not defined; datasets must bring their own fields")
    if caps["field_gradients"] and "field_gradients" in needed:
        def gradients() -> str | None:
            G = np.asarray(scene.field_gradients(states, points))
            want = (*states.shape[:2], len(points), scene.field_dim, scene.body_dim)
            if G.shape != want:
                return (f"field_gradients(states (n, T, S), points (N, dim_B)) must return ∇_X q of shape "
                        f"(n, T, N, A, dim_B) = {want}, got {G.shape}")
            if not np.isfinite(G).all():
                return "field_gradients returned non-finite values"
            return _gradients_match_fields(scene, states, points, G) if caps["fields"] else None
        _run(report, "field gradients ∇_X q (shapes, finite, against central differences of fields)", gradients)
    if not caps["true_energies"]:
        report.skipped.append("true_energy_parts(): not defined; no potential or conservation check")
        return _finish(report, raise_on_problem)

    def energies() -> str | None:
        kin, pot = scene.true_energy_parts(states)
        if np.shape(kin) != states.shape[:2] or np.shape(pot) != states.shape[:2]:
            return f"true_energy_parts(states (n, T, S)) must return two (n, T) arrays, got {np.shape(kin)}, {np.shape(pot)}"
        return None

    if not _run(report, "reference energies (shapes)", energies):
        return _finish(report, raise_on_problem)
    gradient_potential = potential_ok and bool(scene.potential(rule).needs_gradient)
    if caps["fields"] and gradient_potential and not caps["field_gradients"]:
        report.skipped.append("potential V against the scene's own potential energy: its V needs ∇_X q, and the "
                              "scene defines no field_gradients() to compare with (only the gradient loss, "
                              "model.gradient_weight > 0, needs it)")
    elif caps["fields"] and potential_ok:  # (a potential that failed its own check is reported once)
        def against() -> str | None:
            V = scene.potential(rule)
            q, _ = scene.fields(states[:, :: max(1, n_times // 4)], points)
            flat = torch.as_tensor(np.asarray(q).reshape(-1, len(points), scene.field_dim), dtype=rule.weights.dtype)
            G = None
            if V.needs_gradient:
                G = torch.as_tensor(np.asarray(scene.field_gradients(states[:, :: max(1, n_times // 4)], points))
                                    .reshape(-1, len(points), scene.field_dim, scene.body_dim), dtype=flat.dtype)
            pulled = V(flat, G).double().numpy()
            _, pot = scene.true_energy_parts(states[:, :: max(1, n_times // 4)])
            gap = float(np.max(np.abs(pulled - np.asarray(pot).reshape(-1)))) / scene.energy_scale
            if gap > potential_tolerance:
                return (f"V of the scene's own fields on {rule_text} differs "
                        f"from true_energy_parts' potential by {gap:.3g} × energy_scale (tolerance {potential_tolerance}): "
                        f"potential() and true_energy_parts() must describe the same energy, in the same units "
                        f"(or the field is not resolved by the rule: raise quadrature_order)")
            return None
        _run(report, "potential V against the scene's own potential energy", against)
    if caps["conservative"]:
        def conserved() -> str | None:
            energy = np.asarray(scene.true_energy(states))
            drift = float(np.max(np.abs(energy - energy[:, :1]))) / scene.energy_scale
            if drift > energy_tolerance:
                return (f"the simulator's total energy drifts by {drift:.3g} × energy_scale over {times[-1]:.3g} s "
                        f"(tolerance {energy_tolerance}) though the scene declares no forces: tighten the simulator's "
                        f"tolerances, or fix true_energy_parts (or declare the forces with generalized_force)")
            return None
        _run(report, "energy conservation of the simulator (conservative scene)", conserved)
    else:
        report.skipped.append("energy conservation: the scene declares non-conservative forces")
    return _finish(report, raise_on_problem)


def _finish(report: SceneReport, raise_on_problem: bool) -> SceneReport:
    if raise_on_problem and report.problems:
        raise SceneCheckError(str(report))
    return report
