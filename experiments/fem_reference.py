"""The finite-element reference (lnf.fem, scikit-fem) checked and measured: is it the FEM it claims, how far is it
from the continuum, and what does its time stepping cost?

    python -m experiments.fem_reference            # all three parts (about 2 minutes on 2 cores)
    python -m experiments.fem_reference --part mesh

- ``assembly``: the batched internal force and tangent stiffness that the references use (sparse products with
  scikit-fem's discrete gradient) against scikit-fem's own assembly of ∫ P : ∇v dX and ∫ ∇v : A : ∇u dX, and the
  tangent against central differences of the force, on the 2-D cantilever and the 3-D soft body.
- ``mesh``: the discretisation error of the 2-D cantilever (the first bending period about the gravity equilibrium
  on Q1 meshes 20 × 8, 40 × 16 (the scene's), 80 × 32 and 160 × 64, and on triangles), the yardstick for "the
  same reference within discretisation error".
- ``stepping``: the 3-D soft body released from its modal release for 1 s, velocity Verlet at half its CFL step
  against the implicit midpoint rule at 5×, 10× and 20× that step: seconds and the displacement error against a
  Verlet run at a quarter of the step.
Prints only; every number is measured in the run.
"""
from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from lnf.fem.time_stepping import implicit_midpoint, verlet
from lnf.scenes import ElasticCantilever, SoftBody


def assembly() -> None:
    for label, scene in [("2-D cantilever, 40 × 16 Q1", ElasticCantilever()),
                         ("3-D soft body, 20 × 6 × 4 Q1 hexahedra", SoftBody())]:
        body = scene.body
        u = 0.3 * scene.modal_reference()[1] * 0.05 + scene.modal_reference()[0]
        force = body.internal_force(u[None])[0]
        own = body.assembled_internal_force(u)
        K, K_own = body.tangent_stiffness(u), body.assembled_tangent_stiffness(u)
        rng = np.random.default_rng(0)
        direction = rng.standard_normal(u.shape)
        eps = 1e-6
        df = -(body.internal_force((u + eps * direction)[None])[0] - body.internal_force((u - eps * direction)[None])[0])
        df /= 2 * eps
        t0 = time.perf_counter()
        body.tangent_stiffness(u)
        t_ours = time.perf_counter() - t0
        t0 = time.perf_counter()
        body.assembled_tangent_stiffness(u)
        t_own = time.perf_counter() - t0
        print(f"{label}: {body.dim * body.n_nodes} dofs")
        print(f"  force vs scikit-fem's assembly: max |Δ| = {np.abs(force - own).max():.2e} N "
              f"(max |f| = {np.abs(own).max():.3g})")
        print(f"  tangent vs scikit-fem's assembly: max |ΔK| = {abs(K - K_own).max():.2e} (max |K| = {abs(K_own).max():.3g});"
              f" {t_ours * 1e3:.0f} ms against {t_own * 1e3:.0f} ms")
        print(f"  K·δ vs central differences of the force: relative "
              f"{np.abs((K @ direction.reshape(-1)).reshape(u.shape) - df).max() / np.abs(df).max():.2e}")


def first_period(scene: ElasticCantilever) -> float:
    """2π/ω₁ of the first mode about the gravity equilibrium [s]."""
    u_g, _, K = scene.modal_reference()
    free = scene.free_dofs
    mass = sp.diags(np.repeat(scene.nodal_mass, scene.dim)[free]).tocsc()
    value = spla.eigsh(K[free][:, free].tocsc(), k=1, M=mass, sigma=0, which="LM")[0][0]
    return float(2 * np.pi / np.sqrt(value))


def mesh() -> None:
    periods = {}
    for cells in [(20, 8), (40, 16), (80, 32), (160, 64)]:
        periods[cells] = first_period(ElasticCantilever(mesh=cells))
    finest = periods[(160, 64)]
    print("2-D cantilever, first bending period about the gravity equilibrium (Q1 quadrilaterals):")
    for cells, T in periods.items():
        print(f"  {cells[0]:>3} × {cells[1]:<3} {T:.5f} s   ({100 * (T / finest - 1):+.3f} % of 160 × 64)")
    tri = SoftBody(box=(1.0, 0.4), cells=(40, 16), cell_kind="tri", material="svk", young=200.0, poisson=0.3,
                   deflection_range=(-0.15, 0.15), tip_speed_range=(-0.5, 0.5))
    T = first_period(tri)
    print(f"  40 × 16 × 2 linear triangles (the same nodes) {T:.5f} s ({100 * (T / finest - 1):+.3f} %)")


def stepping() -> None:
    scene = SoftBody()
    body = scene.body
    u0 = scene.modal_release(np.array([0.05]))
    v0 = np.zeros_like(u0)
    times = np.linspace(0.0, 1.0, 11)
    load = np.zeros((1, 2))

    def force(u: np.ndarray, t: float, index: np.ndarray) -> np.ndarray:
        return scene.applied_force(u, t, load[index])

    h = scene.time_step
    t0 = time.perf_counter()
    ref, _ = verlet(body, force, u0, v0, times, 0.25 * h)
    t_ref = time.perf_counter() - t0
    scale = np.abs(ref - ref[:, :1]).max()
    t0 = time.perf_counter()
    us, _ = verlet(body, force, u0, v0, times, h)
    print(f"3-D soft body, {body.dim * body.n_nodes} dofs, 1 s from the modal release δ = 0.05 m "
          f"(motion {scale:.3g} m; reference: Verlet at {0.25 * h * 1e3:.3g} ms, {t_ref:.1f} s):")
    print(f"  Verlet at {h * 1e3:.3g} ms (half the CFL step): {time.perf_counter() - t0:.1f} s, "
          f"error {np.abs(us - ref).max() / scale:.2e} of the motion")
    for factor in (5, 10, 20):
        t0 = time.perf_counter()
        us, _, newton = implicit_midpoint(body, force, u0, v0, times, factor * h)
        print(f"  implicit midpoint at {factor * h * 1e3:.3g} ms ({factor}×): {time.perf_counter() - t0:.1f} s, "
              f"error {np.abs(us - ref).max() / scale:.2e} of the motion, ≤ {newton} Newton iterations a step")


PARTS = {"assembly": assembly, "mesh": mesh, "stepping": stepping}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.fem_reference", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--part", choices=sorted(PARTS), nargs="+", default=list(PARTS))
    args = parser.parse_args(argv)
    print(f"{platform.machine()}, {torch.get_num_threads()} torch threads, torch {torch.__version__}")
    for name in args.part:
        PARTS[name]()


if __name__ == "__main__":
    main()
