"""Roofline of the reduced dynamics: measured time of one RK4 step against its FLOP bound, same run.

    python experiments/roofline.py                 # widths 64/128/256 × 1…64 trajectories, GL 8² (default)
    python experiments/roofline.py --smoke

The bound of a step is the matmul FLOPs it needs — value, J and H of the modulated SIREN at the
quadrature points, four accelerations per RK4 step — divided by the best matmul throughput measured
on this machine in the same run (large float32 GEMMs). The default configuration (width 256, depth 2,
Gauss–Legendre 8², the 16 test trajectories rolled out at once) is marked. Writes roofline.csv,
roofline.png and summary.md into outputs/studies/roofline/.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import studylib as S  # noqa: E402

DEFAULT = {"width": 256, "batch": 16}


def timeit(fn, min_seconds: float = 0.3, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    n, start = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        elapsed = time.perf_counter() - start
        if elapsed >= min_seconds and n >= 3:
            return elapsed / n


def matmul_peak(sizes) -> tuple[float, str]:
    """Best float32 GEMM throughput [FLOP/s] over `sizes` (m, k, n)."""
    import torch

    best, shape = 0.0, ""
    for m, k, n in sizes:
        a, b = torch.randn(m, k), torch.randn(k, n)
        rate = 2 * m * k * n / timeit(lambda: a @ b)
        if rate > best:
            best, shape = rate, f"{m}×{k} @ {k}×{n}"
    return best, shape


def step_flops(batch: int, points: int, width: int, depth: int, latent: int, in_dim: int, out_dim: int) -> float:
    """Matmul FLOPs of one RK4 step: 4 accelerations, each a jet of order 2 (value, J, H) at every point."""
    streams = 1 + latent + latent * (latent + 1) // 2
    per_point = 2 * in_dim * width + (depth - 1) * streams * 2 * width * width + streams * 2 * width * out_dim
    return 4.0 * batch * points * per_point


def baselines(study: S.Study, peak: float, batch: int, order: int) -> list[dict]:
    """The same RK4 step for the baselines (their FLOPs: the dense products of one acceleration, × 4)."""
    import torch

    from lnf.baselines import FullOrderModel, LatentMLPDynamics, PODGalerkin
    from lnf.integrators.rk4 import RK4
    from lnf.model import LagrangianNeuralField
    from lnf.quadrature import GaussLegendre
    from lnf.scenes import LiftedPendulum

    scene, rk4, smoke = LiftedPendulum(), RK4(), study.mode == "smoke"
    rows = []
    pod = PODGalerkin(scene, latent_dim=1, quadrature=GaussLegendre(order))
    pod.field.modes.normal_()
    pod.fitted.fill_(True)
    nb, N = pod.field.basis.size, order**2
    mlp_width = 64
    lnf = LagrangianNeuralField(scene, width=16 if smoke else 64, dynamics={
        "_target_": "lnf.baselines.latent_mlp.LatentMLPDynamics", "width": mlp_width, "iterations": 0})
    lnf.latent_dynamics.fitted.fill_(True)
    fom = FullOrderModel(scene, resolution=16 if smoke else 64)
    cases = [("pod", pod.dynamics(), 1, 4.0 * batch * (2 * N * nb * 2 + 6 * N)),
             ("latent_mlp", lnf.dynamics(), 1, 4.0 * batch * 2 * (2 * mlp_width + mlp_width**2 + mlp_width)),
             ("full_order", fom.dynamics(), fom.latent_dim, 4.0 * batch * 4 * fom.latent_dim)]
    with torch.no_grad():
        for name, dyn, dim, flops in cases:
            q, v = 0.5 * torch.randn(batch, dim), torch.randn(batch, dim)
            seconds = timeit(lambda: rk4.step(dyn, (q, v), 0.05, 0.0), min_seconds=0.05 if smoke else 0.5)
            rows.append({"method": name, "width": "", "batch": batch, "points": N if name == "pod" else "",
                         "flops": flops, "seconds": seconds, "bound_seconds": flops / peak,
                         "ratio": seconds * peak / flops, "gflops_achieved": flops / seconds / 1e9,
                         "matmul_peak_gflops": peak / 1e9, "default": False})
            print(f"[roofline] {name:>10}, B={batch:>2}: {seconds * 1e3:8.3f} ms/step, {seconds * peak / flops:7.1f}× its bound",
                  flush=True)
    return rows


def main(argv=None) -> None:
    import numpy as np
    import torch

    from lnf.integrators.rk4 import RK4
    from lnf.model import LagrangianNeuralField
    from lnf.quadrature import GaussLegendre
    from lnf.scenes import LiftedPendulum

    def extra(p):
        p.add_argument("--order", type=int, default=8, help="Gauss–Legendre nodes per axis inside the dynamics")

    study, args = S.parse_args("roofline", __doc__, argv, extra)
    torch.set_num_threads(study.threads)
    torch.manual_seed(0)
    smoke = study.mode == "smoke"
    widths = [16, 32] if smoke else [64, 128, 256]
    batches = [1, 2] if smoke else [1, 4, 16, 64]
    peak, shape = matmul_peak([(256, 64, 64)] if smoke else [(4096, 256, 256), (4096, 512, 512), (2048, 1024, 1024)])
    print(f"[roofline] matmul peak {peak / 1e9:.1f} GFLOP/s ({shape}) on {study.machine()}")
    rows = []
    rk4 = RK4()
    with torch.no_grad():
        for w in widths:
            model = LagrangianNeuralField(LiftedPendulum(), width=w, quadrature=GaussLegendre(args.order)).eval()
            dyn = model.dynamics()
            N = len(dyn.points)
            for b in batches:
                q, v = 0.5 * torch.randn(b, 1), torch.randn(b, 1)
                seconds = timeit(lambda: rk4.step(dyn, (q, v), 0.05, 0.0), min_seconds=0.05 if smoke else 0.5)
                flops = step_flops(b, N, w, model.field.depth, 1, 2, 1)
                bound = flops / peak
                rows.append({"method": "lnf", "width": w, "batch": b, "points": N, "flops": flops, "seconds": seconds,
                             "bound_seconds": bound, "ratio": seconds / bound, "gflops_achieved": flops / seconds / 1e9,
                             "matmul_peak_gflops": peak / 1e9, "default": w == DEFAULT["width"] and b == DEFAULT["batch"]})
                print(f"[roofline] width {w:>3}, B={b:>2}: {seconds * 1e3:8.2f} ms/step, bound {bound * 1e3:7.2f} ms, "
                      f"{seconds / bound:5.1f}× the bound", flush=True)
    rows += baselines(study, peak, batches[-2] if len(batches) > 1 else batches[0], args.order)
    csv_path = study.write_csv("roofline.csv", rows)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    f = np.array([r["flops"] for r in rows])
    xs = np.geomspace(f.min() / 2, f.max() * 2, 50)
    ax.plot(xs, xs / peak, "k-", label=f"bound: FLOPs / {peak / 1e9:.0f} GFLOP/s (matmul peak, same run)")
    ax.plot(xs, 3 * xs / peak, "k--", lw=0.8, label="3× the bound")
    for w, mk in zip(widths, "os^"):
        sel = [r for r in rows if r["method"] == "lnf" and r["width"] == w]
        ax.plot([r["flops"] for r in sel], [r["seconds"] for r in sel], marker=mk, label=f"width {w} (B = {batches})")
    for r in rows:
        if r["method"] != "lnf":
            ax.scatter([r["flops"]], [r["seconds"]], marker=S.MARKERS[r["method"]], color=S.COLORS[r["method"]], s=60,
                       label=f"{S.LABELS[r['method']]} (B = {r['batch']}), {r['ratio']:.0f}× its bound")
    dflt = [r for r in rows if r["default"]]
    if dflt:
        ax.scatter([dflt[0]["flops"]], [dflt[0]["seconds"]], s=250, facecolors="none", edgecolors="r", lw=2,
                   label=f"default: width 256, B = 16 ({dflt[0]['ratio']:.1f}× bound)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"matmul FLOPs of one RK4 step (value, J, H at {args.order}² Gauss–Legendre points)")
    ax.set_ylabel("measured time of one RK4 step [s]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(f"Roofline of the reduced dynamics — {S.caption(study, 'python experiments/roofline.py')}", fontsize=8)
    fig_path = S.save_figure(fig, study.out / "roofline.png")
    text = (f"# Roofline ({study.mode} settings)\n\nMachine: {study.machine()}; matmul peak {peak / 1e9:.1f} GFLOP/s "
            f"({shape}). Command: `python experiments/roofline.py`.\n\n"
            + (f"Default configuration (width 256, B = 16, GL {args.order}²): {dflt[0]['seconds'] * 1e3:.2f} ms per RK4 step, "
               f"{dflt[0]['ratio']:.2f}× the bound.\n\n" if dflt else "")
            + S.markdown_table(rows, [("method", "method"), ("width", "width"), ("batch", "B"), ("points", "points"), ("flops", "FLOPs/step"),
                                      ("seconds", "s/step"), ("bound_seconds", "bound s"), ("ratio", "× bound"),
                                      ("gflops_achieved", "GFLOP/s")]))
    summary = S.write_text_atomic(study.out / "summary.md", text)
    study.finish([csv_path, fig_path, summary])


if __name__ == "__main__":
    main()
