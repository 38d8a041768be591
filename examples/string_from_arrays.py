"""Your own trajectories, brought as arrays (the second example of docs/own_system.md).

A simulator of your own (here a lumped-mass linear finite-element model of a vibrating string on a graded
mesh of 65 nodes, time-stepped by Störmer–Verlet) gives fields at its nodes; lnf trains on them with a scene
that gives only the Lagrangian: no simulate(), no fields().

    PYTHONPATH=examples python -m string_from_arrays            # writes data/string_from_arrays.h5
    PYTHONPATH=examples python -m lnf.train --config-dir examples/conf +experiment=string_from_arrays
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import torch

from lnf.scenes import Scene
from lnf.trajectories import Trajectories, write_dataset
from vibrating_string import TensionPotential


class StringLagrangian(Scene):
    """L = ½∫ρ q̇² dX − ½∫τ (∂q/∂X)² dX on X ∈ [0, length], fixed ends: the Lagrangian alone."""

    field_dim = 1

    def __init__(self, length: float = 1.0, density: float = 1.0, tension: float = 1.0, amplitude: float = 0.1):
        self.length, self.rho, self.tension, self.amplitude = float(length), float(density), float(tension), float(amplitude)
        self.bounds = [[0.0, self.length]]
        omega = np.pi * np.sqrt(self.tension / self.rho) / self.length
        self.energy_scale = 0.25 * self.rho * self.length * (omega * self.amplitude) ** 2  # mode 1 at amplitude

    def params(self) -> dict:
        return {"length": self.length, "density": self.rho, "tension": self.tension, "amplitude": self.amplitude}

    def density(self, points: torch.Tensor) -> torch.Tensor:
        return torch.full(points.shape[:-1], self.rho, dtype=points.dtype, device=points.device)

    def potential(self, quadrature) -> TensionPotential:
        return TensionPotential(quadrature.weights, self.tension)

    def clamp_factor(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = points[..., 0] / self.length
        return 4 * x * (1 - x), (4 * (1 - 2 * x) / self.length)[..., None]


def simulate_fem(scene: StringLagrangian, n: int, n_times: int, dt: float, nodes: int, rng: np.random.Generator,
                 substeps: int = 10) -> Trajectories:
    """`n` runs of the lumped-mass FEM string from u0 = a sin(πX/L), u̇0 = b ω sin(πX/L) (a, b drawn with `rng`)."""
    s = np.linspace(0.0, 1.0, nodes)
    x = scene.length * (s - 0.15 * np.sin(2 * np.pi * s) / np.pi)  # graded: the cells vary by a factor ≈ 1.9
    h = np.diff(x)
    mass = scene.rho * (np.r_[h, 0] + np.r_[0, h]) / 2  # lumped nodal masses = ρ × nodal lengths
    stiff = np.zeros((nodes, nodes))
    for e, k in enumerate(scene.tension / h):
        stiff[e:e + 2, e:e + 2] += k * np.array([[1, -1], [-1, 1]])
    free = slice(1, nodes - 1)  # the two end nodes stay fixed
    omega = np.pi * np.sqrt(scene.tension / scene.rho) / scene.length
    a, b = (rng.uniform(-1, 1, (n, 1)) * scene.amplitude for _ in range(2))
    u, v = a * np.sin(np.pi * x / scene.length), b * omega * np.sin(np.pi * x / scene.length)
    u[:, [0, -1]] = v[:, [0, -1]] = 0.0
    force = lambda u: -(u @ stiff.T)[:, free] / mass[free]  # noqa: E731
    q, qdot, kin, pot = [], [], [], []
    for _ in range(n_times):
        q.append(u.copy()), qdot.append(v.copy())
        kin.append(0.5 * (v ** 2 * mass).sum(-1)), pot.append(0.5 * np.einsum("ni,ij,nj->n", u, stiff, u))
        for _ in range(substeps):  # Störmer–Verlet (velocity form)
            v[:, free] += 0.5 * dt / substeps * force(u)
            u[:, free] += dt / substeps * v[:, free]
            v[:, free] += 0.5 * dt / substeps * force(u)
    return Trajectories(points=x[:, None], times=dt * np.arange(n_times), fields=np.stack(q, 1),
                        velocities=np.stack(qdot, 1), weights=mass / scene.rho,
                        kinetic=np.stack(kin, 1), potential=np.stack(pot, 1))


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    data_dir = Path(os.environ.get("LNF_DATA_DIR", Path(os.environ.get("LNF_ROOT", ".")) / "data"))
    p.add_argument("path", nargs="?", type=Path, default=data_dir / "string_from_arrays.h5",
                   help="where to write (default: where the experiment's data.path looks, {data_dir}/…)")
    p.add_argument("--trajectories", type=int, nargs=3, default=[24, 4, 8], metavar=("TRAIN", "VAL", "TEST"))
    p.add_argument("--times", type=int, default=100, help="samples per trajectory, dt = 0.05 s")
    p.add_argument("--nodes", type=int, default=65)
    args = p.parse_args(argv)
    scene, rng = StringLagrangian(), np.random.default_rng(0)
    runs = simulate_fem(scene, sum(args.trajectories), args.times, 0.05, args.nodes, rng)
    n_train, n_val, _ = args.trajectories
    path = write_dataset(args.path, runs.select(slice(0, n_train)), runs.select(slice(n_train, n_train + n_val)),
                         runs.select(slice(n_train + n_val, None)), scene=scene, observed_fraction=0.5, overwrite=True)
    print(f"wrote {path}: {len(runs)} trajectories × {args.times} samples on {args.nodes} nodes")
    return path


if __name__ == "__main__":
    main()
