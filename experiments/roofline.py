"""Roofline of the reduced dynamics: measured time of one RK4 step against its FLOP bound, same run.

    python -m experiments.roofline                 # widths 64/128/256 × 1…64 trajectories, GL 8² (default)
    python -m experiments.roofline --smoke
    python -m experiments.roofline --scene bump    # the scene's latent dimension, field and quadrature
    python -m experiments.roofline --scene elastic # + the ∇_X φ jets of its strain energy

The bound of a step is the matmul FLOPs it needs — value, J and H of the modulated SIREN at the
quadrature points (and, where the potential depends on the field gradient, ∇_X φ and ∂(∇_X φ)/∂q̃), four
accelerations per RK4 step — divided by the best matmul throughput measured on this machine in the same
run (large float32 GEMMs). The experiment's configuration (on the pendulum width 256, depth 2, Gauss–Legendre
8², the 16 test trajectories rolled out at once) is marked. Writes roofline.csv, roofline.png and
summary.md into outputs/studies/roofline/.

The count is that of `ModulatedSiren.jet`'s forward-mode streams: 1 value, d first q̃-derivatives,
d(d+1)/2 second ones, and on a scene whose potential needs ∇_X φ (the elastic scenes' strain energy) dim_B
X-derivatives and dim_B·d mixed ones. It times the exact pullback (`dynamics=lagrangian`); the elastic
experiment rolls out a Chebyshev table built from it (`dynamics=tabulated`), whose cost is charted by
pareto.py. POD-Galerkin's FLOP count is that of a scalar field's values at d = 1, so it is drawn on the
pendulum and the bump only.
"""
from __future__ import annotations

import sys
import time
from typing import Any

from experiments import studylib as S

DEFAULT_BATCH = 16  # the test set's 16 trajectories, rolled out at once


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


def jet_streams(latent: int, in_dim: int, spatial: bool) -> int:
    """Forward-mode streams of one order-2 jet (`ModulatedSiren.jet(order=2, spatial=...)`): value, d first and
    d(d+1)/2 second q̃-derivatives, and with `spatial` dim_B X-derivatives and dim_B·d mixed ones."""
    streams = 1 + latent + latent * (latent + 1) // 2
    return streams + (in_dim + in_dim * latent if spatial else 0)


def step_flops(batch: int, points: int, width: int, depth: int, latent: int, in_dim: int, out_dim: int,
               spatial: bool = False) -> float:
    """Matmul FLOPs of one RK4 step: 4 accelerations, each an order-2 jet at every point (the first layer's
    derivatives are constants, so only its values are a product)."""
    streams = jet_streams(latent, in_dim, spatial)
    per_point = 2 * in_dim * width + (depth - 1) * streams * 2 * width * width + streams * 2 * width * out_dim
    return 4.0 * batch * points * per_point


def order_text(order: Any) -> str:
    """'8²' for a square Gauss–Legendre rule, '12×6' for a rectangular one."""
    if isinstance(order, (list, tuple)):
        return f"{order[0]}²" if len(set(order)) == 1 else "×".join(str(o) for o in order)
    return f"{order}²"


def scene_of(study: S.Study) -> tuple[Any, int, Any, int, bool, bool]:
    """The study's scene (built from its composed experiment config) and the experiment's latent dimension,
    Gauss–Legendre order (an int or one per axis), SIREN width, clamp, and whether its potential needs ∇_X φ."""
    from omegaconf import OmegaConf

    from lnf.model import build
    from lnf.quadrature import GaussLegendre

    cfg = study.composed()
    scene = study.scene_object()
    quadrature = OmegaConf.to_container(cfg.quadrature, resolve=True)
    if not isinstance(build(quadrature), GaussLegendre):
        sys.exit(f"roofline.py --scene {study.scene}: expected the experiment to use a Gauss–Legendre quadrature "
                 f"(quadrature=gauss_legendre), got {cfg.quadrature.get('_target_')!r}")
    spatial = bool(scene.potential(build(quadrature).build(scene.bounds)).needs_gradient)
    return (scene, int(cfg.model.latent_dim), quadrature["order"], int(cfg.model.width),
            bool(cfg.model.get("clamp", False)), spatial)


def baselines(study: S.Study, scene: Any, latent: int, peak: float, batch: int, order: Any, spatial: bool) -> list[dict]:
    """The same RK4 step for the baselines (their FLOPs: the dense products of one acceleration, × 4)."""
    import torch

    from lnf.baselines import FullOrderModel, PODGalerkin
    from lnf.integrators.rk4 import RK4
    from lnf.model import LagrangianNeuralField
    from lnf.quadrature import GaussLegendre

    rk4, smoke = RK4(), study.mode == "smoke"
    rows, cases = [], []
    N, mlp_width, d = len(GaussLegendre(order).build(scene.bounds).points), 64, latent
    if d == 1 and not spatial and scene.field_dim == 1:  # the FLOP count below is that of a scalar field's values
        pod = PODGalerkin(scene, latent_dim=1, quadrature=GaussLegendre(order))
        pod.field.modes.normal_()
        pod.fitted.fill_(True)
        cases.append(("pod", pod.dynamics(), 1, 4.0 * batch * (2 * N * pod.field.basis.size * 2 + 6 * N)))
    lnf = LagrangianNeuralField(scene, latent_dim=d, width=16 if smoke else 64, dynamics={
        "_target_": "lnf.baselines.latent_mlp.LatentMLPDynamics", "width": mlp_width, "iterations": 0})
    lnf.latent_dynamics.fitted.fill_(True)
    # one acceleration: (q̃, q̃̇) ∈ ℝ²ᵈ → width → width → ℝᵈ
    cases.append(("latent_mlp", lnf.dynamics(), d, 4.0 * batch * 2 * (2 * d * mlp_width + mlp_width**2 + mlp_width * d)))
    if study.supports("full_order"):
        fom = FullOrderModel(scene, resolution=16 if smoke else 64)
        cases.append(("full_order", fom.dynamics(), fom.latent_dim, 4.0 * batch * 4 * fom.latent_dim))
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

    def extra(p):
        p.add_argument("--order", type=int, default=None,
                      help="Gauss–Legendre nodes per axis inside the dynamics (default: the experiment's)")

    study, args = S.parse_args("roofline", __doc__, argv, extra)
    torch.set_num_threads(study.threads)
    torch.manual_seed(0)
    smoke = study.mode == "smoke"
    scene, latent, order, default_width, clamp, spatial = scene_of(study)
    order = args.order or order
    widths = [16, 32] if smoke else [64, 128, 256]
    batches = [1, 2] if smoke else [1, 4, 16, 64]
    peak, shape = matmul_peak([(256, 64, 64)] if smoke else [(4096, 256, 256), (4096, 512, 512), (2048, 1024, 1024)])
    print(f"[roofline] matmul peak {peak / 1e9:.1f} GFLOP/s ({shape}) on {study.machine()}")
    rows = []
    rk4 = RK4()
    with torch.no_grad():
        for w in widths:
            model = LagrangianNeuralField(scene, latent_dim=latent, width=w, quadrature=GaussLegendre(order),
                                          clamp=clamp).eval()
            dyn = model.dynamics()
            N, depth = len(dyn.points), model.field.depth
            for b in batches:
                q, v = 0.5 * torch.randn(b, latent), torch.randn(b, latent)
                seconds = timeit(lambda: rk4.step(dyn, (q, v), 0.05, 0.0), min_seconds=0.05 if smoke else 0.5)
                flops = step_flops(b, N, w, depth, latent, scene.body_dim, scene.field_dim, spatial)
                bound = flops / peak
                rows.append({"method": "lnf", "width": w, "batch": b, "points": N, "flops": flops, "seconds": seconds,
                             "bound_seconds": bound, "ratio": seconds / bound, "gflops_achieved": flops / seconds / 1e9,
                             "matmul_peak_gflops": peak / 1e9, "default": w == default_width and b == DEFAULT_BATCH})
                print(f"[roofline] width {w:>3}, B={b:>2}: {seconds * 1e3:8.2f} ms/step, bound {bound * 1e3:7.2f} ms, "
                      f"{seconds / bound:5.1f}× the bound", flush=True)
    rows += baselines(study, scene, latent, peak, batches[-2] if len(batches) > 1 else batches[0], order, spatial)
    csv_path = study.write_csv("roofline.csv", rows)

    plt = S.pyplot()

    fig, ax = plt.subplots(figsize=(7.5, 6.2), layout="constrained")
    f = np.array([r["flops"] for r in rows])
    xs = np.geomspace(f.min() / 2, f.max() * 2, 50)
    ax.plot(xs, xs / peak, "k-", lw=1.2, label=f"bound: FLOPs / {peak / 1e9:.0f} GFLOP/s (matmul peak, same run)")
    ax.plot(xs, 3 * xs / peak, "k--", lw=0.8, label="3× the bound")
    for k, w in enumerate(widths):
        sel = [r for r in rows if r["method"] == "lnf" and r["width"] == w]
        ax.plot([r["flops"] for r in sel], [r["seconds"] for r in sel], marker="os^Dv"[k % 5],
                ls=["-", "--", "-.", ":"][k % 4], color=f"C{k}", lw=1.5, alpha=0.85, markeredgecolor="white",
                markeredgewidth=0.6, label=f"LNF width {w} (B = {', '.join(map(str, batches))} trajectories)")
    for r in rows:
        if r["method"] != "lnf":
            ax.scatter([r["flops"]], [r["seconds"]], marker=S.MARKERS[r["method"]], color=S.COLORS[r["method"]], s=60,
                       edgecolors="k", linewidths=0.5, zorder=4,
                       label=f"{S.LABELS[r['method']]} (B = {r['batch']}), {r['ratio']:.0f}× its bound")
    dflt = [r for r in rows if r["default"]]
    if dflt:
        ax.scatter([dflt[0]["flops"]], [dflt[0]["seconds"]], s=250, facecolors="none", edgecolors="r", lw=2, zorder=5,
                   label=f"default: width {default_width}, B = {DEFAULT_BATCH} ({dflt[0]['ratio']:.1f}× bound)")
    jets = "value, J, H, ∇_X φ, ∂(∇_X φ)/∂q̃" if spatial else "value, J, H"
    ax.set_xlabel(f"{S.metric_label('flops')}\n({jets} at {order_text(order)} Gauss–Legendre points)")
    ax.set_ylabel(S.metric_label("seconds"))
    S.log_axes(ax, legend="none")
    S.figure_legend(fig, [ax], ncols=1)
    ax.set_title(f"Roofline of the reduced dynamics, {study.scene} (d = {latent})", fontsize=10)
    fig.suptitle(S.caption(study), fontsize=8)
    fig_path = S.save_figure(fig, study.out / "roofline.png")
    text = (f"# Roofline ({study.scene}, d = {latent}, {study.mode} settings)\n\nMachine: {study.machine()}; matmul "
            f"peak {peak / 1e9:.1f} GFLOP/s ({shape}). Command: `{study.command()}`.\n\n"
            + (f"Default configuration (width {default_width}, B = {DEFAULT_BATCH}, GL {order_text(order)}"
               f"{', exact pullback with ∇_X φ jets' if spatial else ''}): {dflt[0]['seconds'] * 1e3:.2f} ms per RK4 step, "
               f"{dflt[0]['ratio']:.2f}× the bound.\n\n" if dflt else "")
            + S.markdown_table(rows, [("method", "method"), ("width", "width"), ("batch", "B"), ("points", "points"), ("flops", "FLOPs/step"),
                                      ("seconds", "s/step"), ("bound_seconds", "bound s"), ("ratio", "× bound"),
                                      ("gflops_achieved", "GFLOP/s")]))
    summary = S.write_text_atomic(study.out / "summary.md", text)
    study.finish([csv_path, fig_path, summary])


if __name__ == "__main__":
    main()
