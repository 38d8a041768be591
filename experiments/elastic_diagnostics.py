"""Why an elastic reduced model works or fails: how low-dimensional the data is, and what the embedding gets wrong.

    python -m experiments.elastic_diagnostics --content                  # both releases, 16 runs of the FEM model
    python -m experiments.elastic_diagnostics --oracle                   # what a 1-D reduction can reach at best
    python -m experiments.elastic_diagnostics --ckpt outputs/elastic/runs/<run>/checkpoints/last.ckpt

--content simulates 16 runs (5 s) of each release (``scene.release``: the Euler–Bernoulli "shape" and the
"modal" one) and prints the share of the displacement and of the velocity (mass-weighted, from the reference
configuration) that k POD modes leave, and that a cubic manifold over the first 1 or 2 POD coordinates
leaves (for the velocity: outside its tangent space).

--ckpt compares a trained model with the FEM on test trajectories of its own dataset: the pulled-back
kinetic and potential energies T̃, Ṽ along the codes of the true snapshots against the FEM's T and V (a
right Lagrangian gives the same changes), and the relative error of the velocity gradient ∇_X φ̇ = GJ q̃̇
against the FEM's on the model's quadrature points, per column of points along X₁ (the clamp is X₁ = 0).
It measures how far the pulled-back equations are from the encoded motion (:func:`equation_residual`), then
separates the two sources of a wrong reduced frequency:
- the embedding's curve: the FEM's own Lagrangian pulled back through the learned curve u(q̃) = φ(q̃, nodes)
  (M and V of the FEM body, no SIREN quadrature), integrated by DOP853 next to the model's own pullback;
- the curve's tangent at rest: its Rayleigh quotient under the FEM's tangent stiffness K_t (Rayleigh–Ritz: any
  error in the tangent raises the frequency, by the error's share of the strain energy) against the FEM's
  first mode, with that error's share of mass and of strain energy and where along X₁ it lies.
Every number is measured in the run. --oracle and --content also write their table (summary.md, with the machine
and the command) and their numbers (oracle.json, content.json) into <--out>/oracle/ and <--out>/content/ (default
outputs/elastic_diagnostics/), which `python -m experiments.results_tables --collect` copies into results/.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _mass_weighted(scene, x: np.ndarray) -> np.ndarray:
    return x.reshape(-1, 2 * scene.n_nodes) * np.sqrt(np.repeat(scene.nodal_mass, 2))


def _cubic_features(a: np.ndarray) -> np.ndarray:
    k = a.shape[1]
    cols = [np.ones((len(a), 1)), a]
    cols += [(a[:, i] * a[:, j])[:, None] for i in range(k) for j in range(i, k)]
    cols += [(a[:, i] * a[:, j] * a[:, m])[:, None] for i in range(k) for j in range(i, k) for m in range(j, k)]
    return np.concatenate(cols, 1)


def content(release: str, runs: int = 16, seed: int = 0, **scene: object) -> dict[str, object]:
    """POD and cubic-manifold content of `runs` FEM runs of the cantilever (defaults, or `scene` settings)."""
    from lnf.scenes.elastic import ElasticCantilever

    scene = ElasticCantilever(release=release, **scene)
    states = scene.simulate(scene.sample_initial_states(runs, np.random.default_rng(seed)), np.linspace(0, 5, 101))
    u, v, _ = scene.unpack(states)
    U, V = _mass_weighted(scene, u), _mass_weighted(scene, v)
    out: dict[str, object] = {}
    for name, X in (("displacement", U), ("velocity", V)):
        s = np.linalg.svd(X, compute_uv=False)
        out[f"{name}: share outside k POD modes (k = 1…6)"] = np.sqrt(np.maximum(1 - np.cumsum(s**2) / np.sum(s**2), 0))[:6]
    _, _, Vt = np.linalg.svd(U, full_matrices=False)
    for k in (1, 2):
        a = U @ Vt[:k].T
        feats = _cubic_features(a)
        coef, *_ = np.linalg.lstsq(feats, U, rcond=None)
        out[f"displacement outside a cubic {k}-D manifold"] = np.linalg.norm(U - feats @ coef) / np.linalg.norm(U)
        eps, tangents = 1e-6, []
        for m in range(k):
            shifted = a.copy()
            shifted[:, m] += eps
            tangents.append((_cubic_features(shifted) - feats) @ coef / eps)
        T = np.stack(tangents, -1)  # (n, D, k)
        rest = sum(np.sum((V[i] - T[i] @ np.linalg.lstsq(T[i], V[i], rcond=None)[0]) ** 2) for i in range(len(V)))
        out[f"velocity outside its tangent space ({k}-D)"] = np.sqrt(rest) / np.linalg.norm(V)
    return out


def oracle(runs: int = 16, horizon: float = 2.5, seed: int = 0, degree: int = 3, **scene_kw: object) -> dict[str, float]:
    """A reduction that needs no learning: the FEM's own Lagrangian pulled back through a fitted curve.

    The curve u(a), a polynomial of `degree` ≤ 3 in the first POD coordinate a (mass-weighted), is fitted to `runs` training
    runs (5 s); M(a) = Σ_n m_n ‖∂u_n/∂a‖² and V(a) = FEM strain energy + gravity of u(a) are exact for the
    FEM body; a(t) is integrated by DOP853 from the projections of `runs` other runs' initial states and
    compared with them over `horizon` [s] (mass-weighted nodal displacement error, relative, median).
    If this is far above a target, no embedding of one coordinate on this scene can meet it."""
    from scipy.integrate import solve_ivp

    from lnf.scenes.elastic import ElasticCantilever

    scene = ElasticCantilever(**scene_kw)
    w = np.sqrt(np.repeat(scene.nodal_mass, 2))
    train = scene.simulate(scene.sample_initial_states(runs, np.random.default_rng(seed)), np.linspace(0, 5, 101))
    U = _mass_weighted(scene, scene.unpack(train)[0])
    _, _, Vt = np.linalg.svd(U, full_matrices=False)
    mode = Vt[0]
    a = U @ mode
    coef, *_ = np.linalg.lstsq(_cubic_features(a[:, None])[:, : degree + 1], U, rcond=None)  # U(a) = [1, a, …] coef
    coef = np.concatenate([coef, np.zeros((4 - len(coef), coef.shape[1]))])  # (4, D), a polynomial of `degree` ≤ 3

    def curve(x: float) -> tuple[np.ndarray, np.ndarray]:  # U(a), dU/da (mass-weighted)
        return np.array([1, x, x**2, x**3]) @ coef, np.array([0, 1, 2 * x, 3 * x**2]) @ coef

    def rhs(_: float, y: np.ndarray) -> np.ndarray:
        x, xdot = y
        Ux, dU = curve(x)
        d2U = np.array([0, 0, 2, 6 * x]) @ coef
        u = (Ux / w).reshape(1, -1, 2)
        du = dU / w
        force = -scene.body.internal_force(u).reshape(-1)  # ∂(strain energy)/∂u
        dV = force @ du + scene.gravity * (scene.nodal_mass * du.reshape(-1, 2)[:, 1]).sum()
        mass, dmass = dU @ dU, 2 * dU @ d2U
        return np.array([xdot, -(0.5 * dmass * xdot**2 + dV) / mass])

    times = np.arange(0, horizon, 0.05)
    test = scene.simulate(scene.sample_initial_states(runs, np.random.default_rng(seed + 1)), times)
    u_true, v_true, _ = scene.unpack(test)
    U_true, V_true = _mass_weighted(scene, u_true).reshape(runs, len(times), -1), _mass_weighted(scene, v_true).reshape(
        runs, len(times), -1)
    errors, floors = [], []
    for i in range(runs):
        x0 = float(U_true[i, 0] @ mode)
        tangent = curve(x0)[1]
        xdot0 = float(V_true[i, 0] @ tangent / (tangent @ tangent))
        sol = solve_ivp(rhs, (0, times[-1]), [x0, xdot0], t_eval=times, method="DOP853", rtol=1e-9, atol=1e-12)
        pred = np.stack([curve(x)[0] for x in sol.y[0]])
        proj = np.stack([curve(float(x))[0] for x in U_true[i] @ mode])
        norm = np.linalg.norm(U_true[i])
        errors.append(np.linalg.norm(pred - U_true[i]) / norm)
        floors.append(np.linalg.norm(proj - U_true[i]) / norm)
    return {"rollout error in the horizon, median": float(np.median(errors)),
            "rollout error in the horizon, max": float(np.max(errors)),
            "projection onto the curve, median": float(np.median(floors))}


def checkpoint(path: Path, trajectory: int = 0) -> None:
    import h5py
    import torch

    import lnf

    model = lnf.load(path)
    scene = model.scene
    with h5py.File(ROOT / model.checkpoint["data"]["path"], "r") as f:
        points = torch.as_tensor(f["grids/fine"][:])
        fields = torch.as_tensor(f["test/fields"][trajectory])
        velocities = torch.as_tensor(f["test/velocities"][trajectory])
        states = f["test/states"][trajectory]
        train_times = int(model.checkpoint["data"]["train_times"])
        # for the curve diagnostics: every test trajectory over the training horizon, on the coarse grid
        coarse = torch.as_tensor(f["grids/coarse"][:]).double()
        test_fields = torch.as_tensor(f["test/coarse_fields"][:, :train_times]).double()
        test_states = f["test/states"][:, :train_times]
        # for the equation residual: the first 4 test trajectories, every sample, on the fine grid
        first_fields, first_velocities = (torch.as_tensor(f[f"test/{key}"][:4]) for key in ("fields", "velocities"))
        dt = float(f["times"][1] - f["times"][0])
    with torch.no_grad():
        q = model.reduce(points, fields)
        qdot = model.project_velocity(q, points, velocities)
        T, V = (x.numpy() for x in model.dynamics().energies(q, qdot))
    kinetic, potential = scene.true_energy_parts(states)
    print(f"energies along the codes of test trajectory {trajectory} (every 3rd sample of the training horizon):")
    print("   t [s]     T̃      T_FEM    Ṽ − Ṽ(0)  V_FEM − V_FEM(0)")
    for i in range(0, train_times, 3):
        print(f"  {0.05 * i:5.2f}  {T[i]:8.5f} {kinetic[i]:8.5f}  {V[i] - V[0]:8.5f}  {potential[i] - potential[0]:8.5f}")
    # velocity gradients on the model's quadrature points
    quad = model.quadrature_rule.build_for(scene)
    qpts = quad.points.to(q)
    jet = model.field.jet(q, qpts, order=1, spatial=True)
    ours = torch.einsum("bnaki,bi->bnak", jet.GJ, qdot).detach().numpy()
    X = qpts.numpy().astype(np.float64)
    fem = scene.velocity_gradients(states, X)  # the FEM's exact ∇_X u̇ (T, N, 2, 2)
    err = np.linalg.norm((ours - fem).reshape(len(ours), len(X), -1), axis=(0, 2))
    ref = np.linalg.norm(fem.reshape(len(ours), len(X), -1), axis=(0, 2))
    print(f"velocity-gradient relative error: {np.linalg.norm(ours - fem) / np.linalg.norm(fem):.3f} overall; by X₁:")
    cols = np.unique(X[:, 0].round(4))
    print("  " + "  ".join(f"{x:.2f}: {np.sqrt((err[m]**2).sum() / (ref[m]**2).sum()):.2f}"
                           for x in cols for m in [X[:, 0].round(4) == x]))
    residual = equation_residual(model, points, first_fields, first_velocities, dt)
    print("the pulled-back equations against the encoded motion of 4 test trajectories (all samples):")
    for key, value in residual.items():
        print(f"  {key}: {value:.4f}")
    if model.latent_dim != 1:
        print(f"(the curve diagnostics below need d = 1; this model has d = {model.latent_dim})")
        return
    model = model.double()
    print("the FEM's Lagrangian through the learned curve against the model's own pullback "
          f"({len(test_states)} test trajectories, DOP853, error at the FEM nodes):")
    for key, value in embedding_pullback(model, coarse, test_fields, test_states, train_times,
                                         float(model.checkpoint["data"]["dt"])).items():
        print(f"  {key}: {value:.4f}")
    low, high = (float(x) for x in (model.code_low, model.code_high))
    if not (np.isfinite(low) and np.isfinite(high)):
        low, high = -1.0, 1.0
    span = high - low
    print("Rayleigh–Ritz: the learned tangent at rest against the FEM's first mode:")
    for key, value in rayleigh_ritz(model, low - 0.3 * span, high + 0.3 * span).items():
        print(f"  {key}: {value:.4f}")


def equation_residual(model, points, fields, velocities, dt: float) -> dict[str, float]:
    """The pulled-back equations against the encoded motion of stored trajectories (fields, velocities (n, T, N, A)
    on `points`, every `dt` [s]): q̃ = ρ̃(u) and q̃̇ = (dφ)†u̇ at each sample, q̃̈ the fourth-order central difference
    of q̃̇; the model's acceleration ã(q̃, q̃̇) = M̃⁻¹(−c̃ − g̃) against q̃̈: the median and 90th percentile of
    ‖ã − q̃̈‖/‖q̃̈‖, and per code axis the scale s of the best fit q̃̈ ≈ s·ã (s < 1: the equations are too stiff along
    it). The difference underestimates an acceleration at frequency ω by about (ω dt)⁴/30 (0.2 % at ω dt = 0.5)."""
    import torch

    from lnf.closure import code_accelerations

    n, T = fields.shape[:2]
    with torch.no_grad():
        flat = fields.reshape(n * T, *fields.shape[2:])
        q = model.reduce(points, flat)
        qdot = model.project_velocity(q, points, velocities.reshape(flat.shape))
        q, qdot = q.reshape(n, T, -1), qdot.reshape(n, T, -1)
        qddot = code_accelerations(qdot, dt)  # the stencil the closure fits with (lnf/closure.py)
        inner = (slice(None), slice(2, T - 2))
        ours = model.lagrangian_dynamics().acceleration(q[inner].reshape(-1, q.shape[-1]),
                                                        qdot[inner].reshape(-1, q.shape[-1])).reshape(qddot.shape)
    ours, qddot = ours.double().numpy(), qddot.double().numpy()
    rel = np.linalg.norm(ours - qddot, axis=-1) / np.linalg.norm(qddot, axis=-1).clip(1e-300)
    out = {"relative residual, median": float(np.median(rel)), "relative residual, 90th percentile":
           float(np.quantile(rel, 0.9))}
    for i in range(q.shape[-1]):
        out[f"scale s along code axis {i}"] = float((ours[..., i] * qddot[..., i]).sum() / (ours[..., i] ** 2).sum())
    return out


def _equilibrium_code(dyn, low: float, high: float) -> "torch.Tensor":
    """The code (1, 1) of least pulled-back potential on [low, high] (a d = 1 model's rest state)."""
    import torch

    grid = torch.linspace(low, high, 801, dtype=torch.float64)[:, None]
    with torch.no_grad():
        return grid[int(torch.argmin(dyn.potential_energy(grid)))][None]


def rayleigh_ritz(model, low: float, high: float, modes: int = 12) -> dict[str, float]:
    """The learned curve's tangent t = ∂φ/∂q̃ at rest, on the FEM nodes, against the FEM's first mode φ₁ about
    the gravity equilibrium: periods 2π/√(tᵀK_t t / tᵀMt), and the error e = t − cφ₁ (M-orthogonal to φ₁)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla
    import torch

    scene = model.scene
    u_g, mode, K = scene.modal_reference()
    nodes = torch.as_tensor(scene.body.nodes)
    q0 = _equilibrium_code(model.lagrangian_dynamics(), low, high)
    with torch.no_grad():
        t = model.field.jet(q0, nodes, order=1).J[0, ..., 0].numpy().reshape(-1)
    m2 = np.repeat(scene.nodal_mass, 2)
    phi = mode.reshape(-1)
    c = (m2 * t) @ phi / ((m2 * phi) @ phi)
    e = t - c * phi
    energy = e @ (K @ e)
    free = scene.free_dofs
    k = min(modes, len(free) - 2)
    values, vectors = spla.eigsh(K[free][:, free].tocsc(), k=k, M=sp.diags(m2[free]).tocsc(), sigma=0, which="LM")
    low_modes = float(((vectors.T @ (m2[free] * e[free])) ** 2 * values).sum() / energy)
    columns = scene.body.nodes[:, 0]  # X₁ of each node
    share = np.bincount(np.repeat(columns < 0.2 * scene.length, 2), weights=e * (K @ e), minlength=2)[1] / energy
    return {"period of the FEM's first mode [s]": 2 * np.pi / np.sqrt(phi @ (K @ phi) / ((m2 * phi) @ phi)),
            "period of the learned tangent under the FEM's K_t [s]": 2 * np.pi / np.sqrt(t @ (K @ t) / ((m2 * t) @ t)),
            "tangent error, share of the mass norm": float(np.sqrt((m2 * e) @ e / ((m2 * t) @ t))),
            "tangent error, share of the strain energy (eᵀK_t e / c²φ₁ᵀK_tφ₁)": float(energy / (c**2 * phi @ (K @ phi))),
            f"  of which outside the first {k} modes": 1 - low_modes,
            "  of which in X₁ < L/5 (next to the clamp)": float(share)}


def embedding_pullback(model, points, fields, states, train_times: int, dt: float) -> dict[str, float]:
    """The FEM Lagrangian pulled back through the learned curve against the model's own pullback (d = 1), on
    test trajectories: small-amplitude periods and the DOP853 rollout error over the training horizon
    (mass-weighted nodal displacement, relative, per trajectory)."""
    import torch
    from scipy.integrate import solve_ivp
    from scipy.interpolate import CubicSpline

    scene = model.scene
    nodes = torch.as_tensor(scene.body.nodes)
    with torch.no_grad():
        codes = torch.stack([model.reduce(points, f[:train_times]) for f in fields])  # (n, T, 1)
    low, high = float(codes.min()), float(codes.max())
    span = max(high - low, 1e-3)
    grid = torch.linspace(low - 0.3 * span, high + 0.3 * span, 401, dtype=torch.float64)[:, None]
    with torch.no_grad():
        jet = model.field.jet(grid, nodes, order=1)
        U, dU = jet.value.numpy(), jet.J[..., 0].numpy()  # u(q̃), ∂u/∂q̃ at the nodes, (401, nn, 2) each
        mass, potential, _ = model.lagrangian_dynamics().static_terms(grid)
        tangents = model.field.jet(codes[:, 0], nodes, order=1).J[..., 0].numpy()  # at each start, (n, nn, 2)
    m = scene.nodal_mass
    g = grid[:, 0].numpy()
    lagrangians = {"FEM through φ": (np.einsum("n,bnk,bnk->b", m, dU, dU), scene.nodal_potential(U)),
                   "model": (mass[:, 0, 0].numpy(), potential.numpy())}
    u_true, v_true, _ = scene.unpack(states[:, :train_times])

    def relative_error(pred: np.ndarray, true: np.ndarray) -> float:
        return float(np.linalg.norm(_mass_weighted(scene, pred - true)) / np.linalg.norm(_mass_weighted(scene, true)))

    times = np.arange(train_times) * dt
    out: dict[str, float] = {}
    for name, (M, V) in lagrangians.items():
        sM, sV = CubicSpline(g, M), CubicSpline(g, V)
        rest = int(np.argmin(V))
        out[f"{name}: small-amplitude period [s]"] = 2 * np.pi * np.sqrt(M[rest] / sV(g[rest], 2))
        errors = []
        for i in range(len(fields)):
            q0, tangent = float(codes[i, 0, 0]), tangents[i]
            qdot0 = float(np.einsum("n,nk,nk->", m, tangent, v_true[i, 0]) / np.einsum("n,nk,nk->", m, tangent, tangent))
            sol = solve_ivp(lambda _, y: [y[1], -(0.5 * sM(y[0], 1) * y[1] ** 2 + sV(y[0], 1)) / sM(y[0])],
                            (0, times[-1]), [q0, qdot0], t_eval=times, method="DOP853", rtol=1e-10, atol=1e-12)
            if not sol.success:  # the curve's potential does not hold the motion (e.g. an untrained model)
                errors.append(float("inf"))
                continue
            with torch.no_grad():
                pred = model.decode(torch.as_tensor(sol.y[0])[:, None], nodes).numpy()
            errors.append(relative_error(pred, u_true[i]))
        out[f"{name}: rollout error in the horizon, median"] = float(np.median(errors))
    with torch.no_grad():
        proj = torch.stack([model.decode(c, nodes) for c in codes]).numpy()
    out["projection onto the curve, median"] = float(np.median([relative_error(p, u) for p, u in zip(proj, u_true)]))
    return out


CURVES = {1: "linear (one POD mode, POD-Galerkin)", 2: "quadratic", 3: "cubic"}


def write_report(folder: Path, name: str, numbers: dict, title: str, table: list[str], argv: list[str]) -> None:
    """`folder`/summary.md (title, machine, command, the table) and `folder`/<name>.json, each written atomically."""
    import json
    import platform

    from lnf.tempfiles import write_text_atomic

    folder.mkdir(parents=True, exist_ok=True)
    command = " ".join(["python -m experiments.elastic_diagnostics", *argv])
    write_text_atomic(folder / f"{name}.json", json.dumps(numbers, indent=1) + "\n")
    write_text_atomic(folder / "summary.md", f"# {title}\n\nMachine: {platform.platform()}, {os.cpu_count()} CPUs. "
                                             f"Command: `{command}`.\n\n" + "\n".join(table) + "\n")
    print(f"wrote {folder / 'summary.md'}")


def oracle_table(results: dict[int, dict[str, float]]) -> list[str]:
    rows = ["| curve | rollout error in the horizon, median (max) | projection onto the curve, median |", "|---|---|---|"]
    for degree, r in results.items():
        rows.append(f"| {CURVES[degree]} | {r['rollout error in the horizon, median']:.3g} "
                    f"({r['rollout error in the horizon, max']:.3g}) | {r['projection onto the curve, median']:.3g} |")
    return rows


def content_table(results: dict[str, dict[str, object]]) -> list[str]:
    def first(values: object, k: int = 3) -> str:
        return " / ".join(f"{float(x):.2g}" for x in np.asarray(values)[:k])

    rows = ["| release | displacement outside 1 / 2 / 3 POD modes | velocity outside 1 / 2 / 3 POD modes | outside a cubic "
            "1-D manifold (displacement / velocity) |", "|---|---|---|---|"]
    for release, r in results.items():
        rows.append(f"| `{release}`{' (the default)' if release == 'modal' else ''} | "
                    f"{first(r['displacement: share outside k POD modes (k = 1…6)'])} | "
                    f"{first(r['velocity: share outside k POD modes (k = 1…6)'])} | "
                    f"{float(r['displacement outside a cubic 1-D manifold']):.2g} / "
                    f"{float(r['velocity outside its tangent space (1-D)']):.2g} |")
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.elastic_diagnostics", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--content", action="store_true", help="low-dimensionality of the two releases")
    parser.add_argument("--runs", type=int, default=16)
    parser.add_argument("--mesh", type=int, nargs=2, default=None, help="--content: FEM mesh (nx ny), default the scene's")
    parser.add_argument("--ckpt", type=Path, default=None, help="a trained elastic checkpoint to diagnose")
    parser.add_argument("--oracle", action="store_true",
                        help="the FEM Lagrangian pulled back through a fitted curve: what d = 1 can reach")
    parser.add_argument("--degree", type=int, nargs="+", default=[3], choices=[1, 2, 3],
                        help="--oracle: degrees of the curve (e.g. 1 2 3)")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "elastic_diagnostics",
                        help="--oracle/--content: folder of their reports (oracle/, content/)")
    args = parser.parse_args(argv)
    given = list(sys.argv[1:] if argv is None else argv)
    if not args.content and args.ckpt is None and not args.oracle:
        parser.error("give --content, --oracle and/or --ckpt")
    extra = {"mesh": args.mesh} if args.mesh else {}
    if args.oracle:
        found = {}
        for degree in sorted(set(args.degree)):
            print(f"oracle d = 1 reduction (degree-{degree} curve over the first POD coordinate, exact FEM "
                  f"Lagrangian), {args.runs} training and {args.runs} test runs, 2.5 s:")
            found[degree] = oracle(args.runs, degree=degree, **extra)
            for key, value in found[degree].items():
                print(f"  {key}: {value:.4f}")
        write_report(args.out / "oracle", "oracle", {str(k): v for k, v in found.items()},
                     f"What one coordinate can reach on the elastic cantilever ({args.runs} + {args.runs} FEM runs)",
                     oracle_table(found), given)
    if args.content:
        found = {}
        for release in ("shape", "modal"):
            print(f"release = {release!r} ({args.runs} runs, 5 s):")
            found[release] = content(release, args.runs, **extra)
            for key, value in found[release].items():
                print(f"  {key}: {np.round(value, 4)}")
        write_report(args.out / "content", "content",
                     {r: {k: np.asarray(v).tolist() for k, v in d.items()} for r, d in found.items()},
                     f"How low-dimensional the two releases are ({args.runs} FEM runs of 5 s each)",
                     content_table(found), given)
    if args.ckpt is not None:
        if not args.ckpt.is_file():
            raise SystemExit(f"no checkpoint at {args.ckpt}")
        checkpoint(args.ckpt)


if __name__ == "__main__":
    main()
