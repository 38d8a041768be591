"""The midpoint rule's solver on a checkpoint's pulled-back dynamics: fixed-point iteration alone (until it stops
contracting, as before NEWTON_AFTER) against today's hand-over to Newton's method, in the same run.

Rolls out `--rows` codes drawn uniformly in the training codes' box (from rest, seed 0) for `--steps` steps of
`--dt` [s] with the default implicit midpoint rule (automatic substeps) on the model's own dynamics (its table where
it has one), and prints for each solver the seconds, the evaluations of the dynamics (rows × calls) and the error
against a float64 copy of the model solved to a tolerance of 1e-12 (relative to the largest |q̃|).

    python -m experiments.bench_midpoint --ckpt outputs/.../checkpoints/last.ckpt [--rows 16] [--steps 40]
"""
from __future__ import annotations

import argparse
import time

import torch

from lnf.integrators import get_integrator
from lnf.integrators import implicit_midpoint
from lnf.model import load


def rollout(model, q0: torch.Tensor, dt: float, steps: int) -> tuple[torch.Tensor, float, int]:
    """(q̃ (B, T, d), seconds, evaluations) of one rollout from rest on the model's dynamics."""
    dynamics = model.dynamics()
    kind, calls = type(dynamics), [0]
    derivatives = kind.hamiltonian_derivatives

    def counted(self, q, p, t=0.0):  # on the class: a closed model's dynamics forward attributes to their base
        calls[0] += q.shape[0]
        return derivatives(self, q, p, t)

    kind.hamiltonian_derivatives = counted
    q0 = q0.to(model.code_low.dtype)
    try:
        start = time.perf_counter()
        traj = model.rollout(q0, torch.zeros_like(q0), dt=dt, steps=steps, dynamics=dynamics, on_divergence="mark",
                             integrator=get_integrator("implicit_midpoint"))
        seconds = time.perf_counter() - start
    finally:
        kind.hamiltonian_derivatives = derivatives
    return traj.q.double(), seconds, calls[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", required=True, help="an lnf checkpoint (last.ckpt) with pulled-back dynamics")
    parser.add_argument("--rows", type=int, default=16)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--dt", type=float, default=0.05)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = load(args.ckpt)
    low, high = model.code_low.double(), model.code_high.double()
    q0 = low + (high - low) * torch.rand(args.rows, low.numel(), generator=torch.Generator().manual_seed(0),
                                         dtype=torch.float64)
    reference, _, _ = rollout(load(args.ckpt).double(), q0, args.dt, args.steps)
    scale = float(reference.abs().max())
    default = implicit_midpoint.NEWTON_AFTER
    print(f"{args.ckpt}: {args.rows} rows × {args.steps} steps of {args.dt} s, {torch.get_num_threads()} thread(s)")
    try:
        for name, after in (("fixed-point iteration alone", 10 ** 9), (f"Newton after {default}", default)):
            implicit_midpoint.NEWTON_AFTER = after
            q, seconds, calls = rollout(model, q0, args.dt, args.steps)  # the table, cached, is built untimed
            print(f"{name:>28}: {seconds:7.2f} s, {calls:8d} evaluations, error vs float64 "
                  f"{float((q - reference).abs().max()) / scale:.2e} (max, relative)")
    finally:
        implicit_midpoint.NEWTON_AFTER = default


if __name__ == "__main__":
    main()
