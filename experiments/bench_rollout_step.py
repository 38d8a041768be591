"""Cost of one reduced RK4 step: batched forward-mode jet (lnf) vs nested jacfwd per trajectory (baseline).

Both evaluate the same M̃, c̃, g̃ of a width-256, depth-2 modulated SIREN at the same Gauss–Legendre points;
the baseline is the straightforward torch.func implementation (J and H by nested jacfwd, one trajectory
at a time). Also prints a FLOP bound: the matmul FLOPs of value, J and H at the quadrature points divided
by the matmul throughput measured on this machine in the same run.

    python -m experiments.bench_rollout_step [--threads 2] [--order 8] [--batch 1 4 16]
"""
from __future__ import annotations

import argparse
import platform
import time

import torch
from torch.func import jacfwd

from lnf.model import LagrangianNeuralField
from lnf.quadrature import GaussLegendre
from lnf.scenes import LiftedPendulum


def timeit(fn, repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - start) / repeats


def nested_jacfwd_acceleration(model: LagrangianNeuralField, dyn, q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Baseline: per trajectory, J = jacfwd(φ), H = jacfwd(jacfwd(φ)), then the same contractions."""
    ww = dyn.density_weights
    out = []
    for b in range(q.shape[0]):
        f = lambda x: model.field(x[None], dyn.points)[0]  # noqa: E731  (N, A)
        value = f(q[b])
        J = jacfwd(f)(q[b])  # (N, A, d)
        H = jacfwd(jacfwd(f))(q[b])  # (N, A, d, d)
        M = torch.einsum("n,nai,naj->ij", ww, J, J)
        c = torch.einsum("n,nai,naj,j->i", ww, J, torch.einsum("najk,k->naj", H, v[b]), v[b])
        dVdq, _ = dyn.potential_fn.gradient(value[None])
        g = torch.einsum("na,nai->i", dVdq[0], J)
        out.append(torch.linalg.solve(M, -c - g))
    return torch.stack(out)


def rk4_step(accel, q, v, h):
    a1 = accel(q, v)
    a2 = accel(q + 0.5 * h * v, v + 0.5 * h * a1)
    a3 = accel(q + 0.5 * h * (v + 0.5 * h * a1), v + 0.5 * h * a2)
    a4 = accel(q + h * (v + 0.5 * h * a2), v + h * a3)
    return q + h / 6 * (v + 2 * (v + 0.5 * h * a1) + 2 * (v + 0.5 * h * a2) + v + h * a3), v + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)


def matmul_throughput(rows: int, width: int) -> float:
    a, w = torch.randn(rows, width), torch.randn(width, width)
    seconds = timeit(lambda: a @ w, repeats=200)
    return 2 * rows * width * width / seconds


def main() -> None:
    p = argparse.ArgumentParser(prog="python -m experiments.bench_rollout_step", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--order", type=int, default=8, help="Gauss–Legendre nodes per axis (N = order²)")
    p.add_argument("--batch", type=int, nargs="+", default=[1, 4, 16])
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--repeats", type=int, default=20)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    model = LagrangianNeuralField(LiftedPendulum(), width=args.width, quadrature=GaussLegendre(args.order)).eval()
    dyn = model.dynamics()
    N, W, depth = len(dyn.points), args.width, model.field.depth
    print(f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, {args.threads} threads")
    print(f"model: width {W}, depth {depth}, d=1; quadrature: Gauss–Legendre {args.order}² = {N} points; dt = 0.05")
    print(f"{'B':>4} {'nested jacfwd [ms/step]':>24} {'lnf jet [ms/step]':>18} {'speed-up':>9} {'jet per traj [ms]':>18} {'FLOP bound [ms]':>16} {'jet/bound':>10}")
    with torch.no_grad():
        for B in args.batch:
            q = 0.5 * torch.randn(B, 1)
            v = torch.randn(B, 1)
            t_nested = timeit(lambda: rk4_step(lambda a, b: nested_jacfwd_acceleration(model, dyn, a, b), q, v, 0.05),
                              repeats=max(2, args.repeats // B))
            t_jet = timeit(lambda: rk4_step(dyn.acceleration, q, v, 0.05), repeats=args.repeats)
            ref = rk4_step(lambda a, b: nested_jacfwd_acceleration(model, dyn, a, b), q, v, 0.05)[0]
            ours = rk4_step(dyn.acceleration, q, v, 0.05)[0]
            assert torch.allclose(ref, ours, rtol=1e-4, atol=1e-5), "the two implementations disagree"
            # matmul FLOPs per acceleration: hidden layers carry 3 streams (value, J, H) of B·N rows
            flops = 4 * (2 * 3 * B * N * W * W * (depth - 1))
            bound = flops / matmul_throughput(max(B * N * 3, 64), W)
            print(f"{B:>4} {t_nested * 1e3:>24.2f} {t_jet * 1e3:>18.2f} {t_nested / t_jet:>8.1f}× "
                  f"{t_jet / B * 1e3:>18.3f} {bound * 1e3:>16.3f} {t_jet / bound:>9.1f}×")


if __name__ == "__main__":
    main()
