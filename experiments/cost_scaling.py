"""Cost scaling: rollout time and peak memory against evaluation points and trajectories rolled out at once.

    python -m experiments.cost_scaling          # models of the reduced stability study (trained if missing)
    python -m experiments.cost_scaling --full   # models of the full stability study

For each method (our model, the black-box latent MLP, POD-Galerkin k = 1, the full-order model) and
each evaluation grid 16² … 256² (16 trajectories), then each batch of 1 … 64 trajectories (64² grid; on a
1-D or 3-D body grids of as many points):
the latent rollout of 100 steps (dt = 0.05 s, each method's default integrator; the faster of two runs), the decoding of the
100 frames on the grid, and the peak resident memory above the level before the call (sampled every
millisecond). The reduced rollout does not touch the evaluation grid, so its cost must stay flat
while decoding grows; the full-order model's state is the grid itself (it is rebuilt at each
resolution), so its rollout grows with it. Writes cost_scaling.csv, cost_scaling.png and summary.md
into outputs/studies/cost_scaling/.
"""
from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path

import numpy as np

from experiments import stability
from experiments import studylib as S


class PeakRSS:
    """Peak resident set size above the level at entry [bytes], sampled every `interval` seconds."""

    def __init__(self, interval: float = 1e-3) -> None:
        self.interval, self.peak, self._stop = interval, 0, threading.Event()

    @staticmethod
    def rss() -> int:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * 4096

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self.rss() - self.base)
            time.sleep(self.interval)

    def __enter__(self) -> "PeakRSS":
        self.base = self.rss()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.rss() - self.base)


def axis_resolution(points: int, dim: int) -> int:
    """The grid resolution per axis of a `dim`-D body with about `points` points (16² = 256 points: 16 per axis
    in 2-D, 256 in 1-D, 6 in 3-D)."""
    return max(1, int(round(points ** (1.0 / dim))))


def measure(model, scene, integrator: str, resolution: int, batch: int, steps: int, seed: int = 0) -> dict:
    """Reduction, rollout of `steps` steps and decoding of `batch` sampled trajectories on a uniform grid of
    `resolution` points per axis, with their wall-clock and peak memory."""
    import torch

    from lnf.evaluation import reduction_subset, trajectory_controls
    from lnf.quadrature import midpoint_grid

    rng = np.random.default_rng(seed)
    states0 = scene.sample_initial_states(batch, rng)
    grid = midpoint_grid(resolution, scene.bounds).float()
    sub = torch.as_tensor(reduction_subset(len(grid), (resolution,) * scene.body_dim,
                                           None if model.state_is_field else 1024))
    q_true, v_true = scene.fields(states0, grid[sub].numpy())
    with torch.no_grad():
        t0 = time.perf_counter()
        q0 = model.reduce(grid[sub], torch.as_tensor(q_true, dtype=torch.float32))
        v0 = model.project_velocity(q0, grid[sub], torch.as_tensor(v_true, dtype=torch.float32))
        reduce_s = time.perf_counter() - t0
        controls = trajectory_controls(scene, states0, q0)  # a scene with loads: each trajectory's load parameters
        model.rollout(q0, v0, dt=0.05, steps=2, integrator=integrator, on_divergence="mark", controls=controls)
        rollout_s = float("inf")
        for _ in range(2):  # the faster of two runs: the first full rollout of a process carries one-off costs
            with PeakRSS() as mem_roll:
                t0 = time.perf_counter()
                traj = model.rollout(q0, v0, dt=0.05, steps=steps, integrator=integrator, on_divergence="mark",
                                     controls=controls)
                rollout_s = min(rollout_s, time.perf_counter() - t0)
        codes = torch.nan_to_num(traj.q.reshape(-1, traj.q.shape[-1]))
        with PeakRSS() as mem_dec:
            t0 = time.perf_counter()
            for i in range(0, codes.shape[0], 32):
                model.decode(codes[i:i + 32], grid)
            decode_s = time.perf_counter() - t0
    return {"points": len(grid), "resolution": resolution, "batch": batch, "steps": steps,
            "reduce_seconds": reduce_s, "rollout_seconds": rollout_s, "rollout_seconds_per_step": rollout_s / steps,
            "decode_seconds": decode_s, "total_seconds": rollout_s + decode_s,
            "rollout_peak_mib": mem_roll.peak / 2**20, "decode_peak_mib": mem_dec.peak / 2**20,
            "diverged_fraction": float(traj.diverged.float().mean())}


def run(study: S.Study, ckpts: dict) -> list[dict]:
    import torch

    import lnf
    from lnf.baselines import FullOrderModel
    from lnf.quadrature import midpoint_grid

    torch.set_num_threads(study.threads)
    smoke = study.mode == "smoke"
    dim = study.scene_object().body_dim
    # the grids of a 2-D body, 8² … 256², with as many points on a body of another dimension
    resolutions = [axis_resolution(n**2, dim) for n in ([8, 16] if smoke else [16, 32, 64, 128, 256])]
    batch_grid = axis_resolution((8 if smoke else 64) ** 2, dim)
    batches = [1, 2] if smoke else [1, 4, 16, 64]
    steps = 5 if smoke else 100
    rows = []
    for m, ckpt in ckpts.items():
        model = lnf.load(ckpt)
        if m != "full_order":  # steady state: a fresh process runs the same rollout 2.5× slower until a large
            with torch.no_grad():  # block has been freed (glibc's dynamic mmap threshold), whatever the grid
                model.decode(torch.zeros(32, model.latent_dim), midpoint_grid(128, model.scene.bounds))
        integ = stability.INTEGRATORS[m][0]
        for r in resolutions:
            mod = FullOrderModel(model.scene, resolution=r) if m == "full_order" else model
            rows.append({"method": m, "integrator": integ, "sweep": "points",
                         **measure(mod, model.scene, integ, r, 2 if smoke else 16, steps)})
            print(f"[cost_scaling] {m:>10} {S.per_axis(r, dim):>5}: rollout {rows[-1]['rollout_seconds']:.3f} s, "
                  f"decode {rows[-1]['decode_seconds']:.3f} s, peak {rows[-1]['decode_peak_mib']:.0f} MiB", flush=True)
        for b in batches:
            rows.append({"method": m, "integrator": integ, "sweep": "batch",
                         **measure(model, model.scene, integ, batch_grid, b, steps)})
            print(f"[cost_scaling] {m:>10} B={b:>3}: rollout {rows[-1]['rollout_seconds']:.3f} s", flush=True)
    return rows


def plot(study: S.Study, rows: list[dict]) -> Path:
    plt = S.pyplot()
    from matplotlib.lines import Line2D

    fig, axes = plt.subplots(1, 3, figsize=(15, 5.2), layout="constrained")
    steps = next((int(round(r["rollout_seconds"] / r["rollout_seconds_per_step"])) for r in rows
                  if r.get("rollout_seconds_per_step")), 100)
    handles = []
    style = dict(alpha=0.85, markeredgecolor="white", markeredgewidth=0.6, markersize=6, lw=1.6)
    for m in S.METHODS:
        pts = sorted((r for r in rows if r["method"] == m and r["sweep"] == "points"), key=lambda r: r["points"])
        bat = sorted((r for r in rows if r["method"] == m and r["sweep"] == "batch"), key=lambda r: r["batch"])
        if not pts:
            continue
        kw = dict(marker=S.MARKERS[m], color=S.COLORS[m], **style)
        x = S.dodged([r["points"] for r in pts], m)  # coincident curves stay side by side
        axes[0].plot(x, [r["rollout_seconds"] for r in pts], "-", **kw)
        axes[0].plot(x, [r["decode_seconds"] for r in pts], ":", **kw)
        axes[1].plot(x, [max(r["rollout_peak_mib"], r["decode_peak_mib"]) for r in pts], S.LINESTYLES[m], **kw)
        axes[2].plot(S.dodged([r["batch"] for r in bat], m),
                     [r["rollout_seconds"] / r["batch"] for r in bat], S.LINESTYLES[m], **kw)
        handles.append(Line2D([], [], marker=S.MARKERS[m], color=S.COLORS[m], ls=S.LINESTYLES[m], label=S.LABELS[m],
                              **{k: v for k, v in style.items() if k != "lw"}))
    handles += [Line2D([], [], color="0.3", ls="-", label=f"left: rollout ({steps} steps)"),
                Line2D([], [], color="0.3", ls=":", label=f"left: decoding ({steps} frames)")]
    n_traj = next((r["batch"] for r in rows if r["sweep"] == "points" and "batch" in r), 16)
    batch_points = next((r["points"] for r in rows if r["sweep"] == "batch"), "")
    axes[0].set_xlabel(f"{S.metric_label('points')} ({n_traj} trajectories)")
    axes[0].set_ylabel("wall-clock [s]")
    axes[0].set_title("Rollout (solid) and decoding (dotted)", fontsize=10)
    axes[1].set_xlabel(f"{S.metric_label('points')} ({n_traj} trajectories)")
    axes[1].set_ylabel(S.metric_label("peak_mib") + "\n(resident set, 1 ms sampling)")
    axes[1].set_title("Peak memory of rollout or decoding", fontsize=10)
    axes[2].set_xlabel(f"{S.metric_label('batch')} ({batch_points}-point grid)")
    axes[2].set_ylabel(f"rollout wall-clock per trajectory [s] ({steps} steps)")
    axes[2].set_title("Batched rollout", fontsize=10)
    for ax in axes:
        S.log_axes(ax, legend="none")
    for ax in axes[:2]:
        S.ticks_at(ax, [r["points"] for r in rows if r["sweep"] == "points"], fmt=lambda v: f"{v:.0f}")
    S.ticks_at(axes[2], [r["batch"] for r in rows if r["sweep"] == "batch"])
    fig.legend(handles=handles, loc="outside lower center", ncols=len(handles), fontsize="small", frameon=False)
    fig.suptitle(f"Cost scaling, {study.scene} ({S.DODGE_NOTE})\n{S.caption(study)}", fontsize=9)
    return S.save_figure(fig, study.out / "cost_scaling.png")


def summary(study: S.Study, rows: list[dict]) -> Path:
    dim = study.scene_object().body_dim
    lines = [f"# Cost scaling ({study.scene}, {study.mode} settings)\n\n",
             f"Machine: {study.machine()}. Command: `{study.command()}`.\n\n"]
    for m in S.METHODS:
        pts = sorted((r for r in rows if r["method"] == m and r["sweep"] == "points"), key=lambda r: r["points"])
        if pts:
            per_step = [r["rollout_seconds_per_step"] for r in pts]
            lines.append(f"- {S.LABELS[m]}: rollout per step from {S.per_axis(pts[0]['resolution'], dim)} to "
                         f"{S.per_axis(pts[-1]['resolution'], dim)}: "
                         f"{S.fmt(per_step[0] * 1e3)} → {S.fmt(per_step[-1] * 1e3)} ms (max/min {max(per_step) / min(per_step):.2f}); "
                         f"decoding {S.fmt(pts[0]['decode_seconds'])} → {S.fmt(pts[-1]['decode_seconds'])} s.\n")
    cols = [("method", "method"), ("sweep", "sweep"), ("points", "points"), ("batch", "trajectories"),
            ("rollout_seconds", "rollout s"), ("rollout_seconds_per_step", "s/step"), ("decode_seconds", "decode s"),
            ("rollout_peak_mib", "rollout peak MiB"), ("decode_peak_mib", "decode peak MiB")]
    lines.append("\n" + S.markdown_table(rows, cols))
    return S.write_text_atomic(study.out / "summary.md", "".join(lines))


def main(argv=None) -> None:
    study, _ = S.parse_args("cost_scaling", __doc__, argv)
    # the models of the stability study (same settings; reused if it already ran)
    trainer = dataclasses.replace(study, name="stability", rows=[],
                                  out=study.out.parent / study.out.name.replace("cost_scaling", "stability"))
    ckpts = stability.train_all(trainer)
    rows = run(study, ckpts)
    csv_path = study.write_csv("cost_scaling.csv", rows)
    study.finish([csv_path, plot(study, rows), summary(study, rows)])


if __name__ == "__main__":
    main()
