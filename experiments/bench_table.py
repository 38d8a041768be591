"""Cost of evaluating a Chebyshev table of the reduced dynamics (lnf.tabulated.ChebyshevTable) at d codes: axis by
axis (the einsum contractions used at d ≤ 2) against one matrix product on the tensor-product basis (used from
d = TENSOR_BASIS_FROM_DIM), in the same run, on a table of random coefficients with the shape a model's has.

    python -m experiments.bench_table [--threads 1] [--dims 2 3 4] [--rows 16 160 1600]
"""
from __future__ import annotations

import argparse
import platform

import numpy as np
import torch

from experiments.bench_rollout_step import timeit
from lnf import tabulated

#: nodes per axis and channels (M̃, Ṽ, a damping and a load's work) of the tables measured, by d
SHAPES = {2: (32, 12), 3: (32, 15), 4: (16, 20)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--dims", type=int, nargs="+", default=[2, 3, 4], choices=sorted(SHAPES))
    parser.add_argument("--rows", type=int, nargs="+", default=[16, 160, 1600])
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"{platform.processor() or platform.machine()}, torch {torch.__version__}, {args.threads} thread(s), float32")
    rng = np.random.default_rng(0)
    for d in args.dims:
        n, channels = SHAPES[d]
        table = tabulated.ChebyshevTable(rng.standard_normal((*[n] * d, channels)), [-1.0] * d, [1.0] * d,
                                         dtype=torch.float32, keep_float64=False)
        for rows in args.rows:
            x = torch.as_tensor(rng.uniform(-1, 1, (rows, d)), dtype=torch.float32)
            cost = {}
            for name, start in (("axis by axis", 99), ("tensor basis", 3)):
                tabulated.TENSOR_BASIS_FROM_DIM = start
                cost[name] = timeit(lambda: table.evaluate_scaled(x, table.coef), repeats=5, warmup=1)
            a, b = cost["axis by axis"], cost["tensor basis"]
            print(f"d = {d} ({n} nodes per axis), {rows:5d} rows: axis by axis {a * 1e3:8.2f} ms, tensor basis "
                  f"{b * 1e3:8.2f} ms, ratio {a / b:.2f}", flush=True)


if __name__ == "__main__":
    main()
