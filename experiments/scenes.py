"""Acceptance measurements of the scenes beyond the pendulum, from their trained checkpoints.

    python -m lnf.train +experiment=<scene> hydra.run.dir=outputs/issue4/<scene>   # train first
    python experiments/scenes.py --scene double_pendulum   # vpt and 20x-horizon energy drift vs the black box
    python experiments/scenes.py --scene bump              # error against number of modes: ours (d = 1) vs POD
    python experiments/scenes.py --scene elastic           # accuracy, energy, speed-up over the FEM model
    python experiments/scenes.py --scene elastic --dynamics tabulated   # … with our tabulated M̃, Ṽ
    python experiments/scenes.py --scene elastic_actuated  # damping and a load not seen in training

Each writes ``outputs/scenes/<scene>/{results.json, summary.md, *.png}``. Every number is measured here,
in one process, on the machine it runs on (threads: all cores unless --threads).
"""
from __future__ import annotations

import argparse
import copy
import inspect
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lnf.baselines.latent_mlp import LatentMLPDynamics  # noqa: E402
from lnf.baselines.pod import PODGalerkin  # noqa: E402
from lnf import metrics as M  # noqa: E402
from lnf.evaluate import ensure_code_range  # noqa: E402
from lnf.evaluation import evaluate_rollouts, long_horizon_energy, trajectory_controls  # noqa: E402
from lnf.model import load  # noqa: E402
from lnf.plotting import save_figure  # noqa: E402
from lnf.train import fit_latent_dynamics  # noqa: E402
from lnf.training.callbacks import write_json_atomic  # noqa: E402
from lnf.training.datamodule import SnapshotDataModule  # noqa: E402


def datamodule_of(model: Any) -> SnapshotDataModule:
    """The checkpoint's own dataset (regenerated if missing)."""
    data = dict(model.checkpoint.get("data") or {})
    if not data:
        raise SystemExit("the checkpoint records no data settings")
    dm = SnapshotDataModule(scene=model.scene, **data)
    dm.prepare_data()
    return dm


def evaluate(model: Any, split: Any, integrator: Any = None, states: np.ndarray | None = None,
             stride: int = 1) -> Any:
    """Roll out the split (or `states`, re-simulated ground truth) on the stored fine grid; `stride` subsamples time.

    Default integrator: the implicit midpoint rule of order 2 (see MIDPOINT)."""
    integrator = MIDPOINT if integrator is None else integrator
    train_horizon = float(split.times[split.train_times])
    if states is None:
        return evaluate_rollouts(model, split.states[:, ::stride], split.times[::stride], split.fine_points,
                                 train_horizon, true_fields=split.fields[:, ::stride],
                                 true_velocities=split.velocities[:, ::stride], integrator=integrator)
    return evaluate_rollouts(model, states[:, ::stride], split.times[::stride], split.fine_points, train_horizon,
                             integrator=integrator)


# the structure-preserving integrator of these scenes: order 2 (the order-4 composition's backward substep
# leaves some double-pendulum rollouts unsolved at dt = 0.05)
MIDPOINT = {"name": "implicit_midpoint", "order": 2}


def _figure() -> tuple[Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(5, 3.4), layout="constrained")


def _ours_against_fem(times: np.ndarray, ours: np.ndarray, fem: np.ndarray, ylabel: str, title: str, path: Path,
                      horizon: float | None = None, n: int = 3) -> Path:
    """One quantity (n_traj, T) over time for the first `n` trajectories, ours (solid) and the FEM's (dotted)."""
    fig, ax = _figure()
    for i in range(min(n, len(ours))):
        ax.plot(times, ours[i], color=f"C{i}")
        ax.plot(times, fem[i], color=f"C{i}", ls=":")
    if horizon is not None:
        ax.axvline(horizon, color="k", ls="--", lw=0.8)
    ax.set_xlabel("t [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(f"{title}\nsolid: ours, dotted: FEM" + (", dashed: training horizon" if horizon else ""), fontsize=8)
    return save_figure(fig, path)


def _tip_figure(ev: Any, path: Path, title: str, horizon: float | None = None) -> Path:
    """The vertical displacement at the free end's mid-point over time, ours against the FEM's."""
    pts = ev.points
    tip = int(np.argmin((pts[:, 0] - pts[:, 0].max()) ** 2 + (pts[:, 1] - pts[:, 1].mean()) ** 2))
    return _ours_against_fem(ev.times, ev.pred_fields[:, :, tip, 1], ev.true_fields[:, :, tip, 1],
                             "tip displacement u₂ [m]", title, path, horizon)


def pick(metrics: dict[str, float], *keys: str) -> dict[str, float]:
    return {k: float(metrics[k]) for k in keys if k in metrics}


# ---------------------------------------------------------------------------------------------------------
def double_pendulum(model: Any, dm: SnapshotDataModule, out: Path, bb_iterations: int = 2000) -> dict[str, Any]:
    split = dm.split("test")
    ours = evaluate(model, split)
    black_box = copy.deepcopy(model)
    black_box.latent_dynamics = LatentMLPDynamics(latent_dim=model.latent_dim, iterations=bb_iterations)
    fit = fit_latent_dynamics(black_box, dm)
    bb = evaluate(black_box, split, "rk4")
    dt = float(split.times[1] - split.times[0])
    horizon = float(split.times[split.train_times])
    steps = int(round(20 * horizon / dt))
    states0 = split.states[:8, 0]  # the first 8 test trajectories (20x horizon: 1000 steps each)
    drift_ours = long_horizon_energy(model, states0, split.fine_points, dt, steps, MIDPOINT)
    drift_bb = long_horizon_energy(black_box, states0, split.fine_points, dt, steps, "rk4")
    keys = ("vpt/median", "vpt/min", "field_rel_l2/in_horizon/median", "field_rel_l2/all/median",
            "projection_rel_l2/all/median", "energy_rel_err/median", "diverged_fraction")
    result = {"ours": {**pick(ours.metrics, *keys), **drift_ours}, "black_box": {**pick(bb.metrics, *keys), **drift_bb},
              "black_box_fit": fit, "long_steps": steps, "long_horizon_s": steps * dt}
    result["drift_ratio_median"] = drift_bb["energy_drift_long/median"] / max(drift_ours["energy_drift_long/median"], 1e-300)
    vpt_ours, vpt_bb = _vpt_per_trajectory(ours), _vpt_per_trajectory(bb)
    fig, ax = _figure()
    ax.hist([vpt_ours, vpt_bb], bins=10, label=[f"ours (median {np.median(vpt_ours):.2f} s)",
                                                 f"black box (median {np.median(vpt_bb):.2f} s)"])
    ax.axvline(horizon, color="k", ls="--", lw=0.8)
    ax.set_xlabel("valid prediction time [s]")
    ax.set_ylabel("test trajectories")
    ax.legend(fontsize=8)
    save_figure(fig, out / "vpt.png")
    return result


def _vpt_per_trajectory(evaluation: Any) -> np.ndarray:
    """`vpt` of every trajectory (the metrics hold only its median and min)."""
    w = np.full(len(evaluation.points), 1.0 / len(evaluation.points))
    return M.valid_prediction_time(evaluation.pred_fields, evaluation.true_fields, w, evaluation.times)


# ---------------------------------------------------------------------------------------------------------
def bump(model: Any, dm: SnapshotDataModule, out: Path, max_modes: int = 12) -> dict[str, Any]:
    split = dm.split("test")
    ours = evaluate(model, split)
    points, values, velocities = (torch.as_tensor(a, dtype=torch.float64) for a in dm.observations("train"))
    pod_rows = []
    for k in range(1, max_modes + 1):
        pod = PODGalerkin(model.scene, latent_dim=k, degree=24).double()
        pod.fit_to_observations(points, values)
        metrics = evaluate(pod, split).metrics
        pod_rows.append({"k": k, **pick(metrics, "field_rel_l2/all/median", "projection_rel_l2/all/median",
                                        "diverged_fraction")})
        print(f"POD k={k}: {pod_rows[-1]}", flush=True)
    # the best any k-mode linear model can do: SVD of the full fine-grid training fields, projection of the test fields
    train = dm.split("train")
    X = train.fields[:, :train.train_times, :, 0].reshape(-1, train.fields.shape[2]).astype(np.float64)
    mean = X.mean(0)
    _, _, Vt = np.linalg.svd(X - mean, full_matrices=False)
    Y = split.fields[..., 0].astype(np.float64)
    oracle = []
    for k in range(1, max_modes + 1):
        R = mean + ((Y - mean) @ Vt[:k].T) @ Vt[:k]
        oracle.append(float(np.median(np.sqrt(((R - Y) ** 2).sum((1, 2)) / (Y**2).sum((1, 2))))))
    ours_err = float(ours.metrics["field_rel_l2/all/median"])
    needed = next((r["k"] for r in pod_rows if r["field_rel_l2/all/median"] <= ours_err), None)
    needed_oracle = next((k + 1 for k, e in enumerate(oracle) if e <= ours_err), None)
    fig, ax = _figure()
    ks = [r["k"] for r in pod_rows]
    ax.semilogy(ks, [r["field_rel_l2/all/median"] for r in pod_rows], "s-", label="POD-Galerkin rollout")
    ax.semilogy(range(1, max_modes + 1), oracle, "k:", label="best linear k-mode projection (full-grid SVD)")
    ax.semilogy([1], [ours_err], "o", ms=9, color="C3", label=f"ours, d = 1 ({ours_err:.3f})")
    ax.axhline(ours_err, color="C3", lw=0.8, ls="--")
    ax.set_xlabel("modes k (POD) / latent dimension d (ours)")
    ax.set_ylabel("test field_rel_l2 (all, median)")
    ax.legend(fontsize=8)
    save_figure(fig, out / "modes.png")
    return {"ours": pick(ours.metrics, "field_rel_l2/all/median", "field_rel_l2/in_horizon/median",
                         "field_rel_l2/extrapolation/median", "projection_rel_l2/all/median", "energy_rel_err/median"),
            "pod": pod_rows, "oracle_projection": oracle, "pod_modes_to_match_ours": needed,
            "oracle_modes_to_match_ours": needed_oracle}


# ---------------------------------------------------------------------------------------------------------
def timed(fn: Callable[[], Any], repeats: int = 2) -> tuple[float, Any]:
    best, result = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return best, result


def elastic(model: Any, dm: SnapshotDataModule, out: Path, target: float = 0.05) -> dict[str, Any]:
    scene, split = model.scene, dm.split("test")
    times = split.times
    in_h = times < times[split.train_times]
    base = evaluate(model, split)
    result: dict[str, Any] = {"ours": pick(base.metrics, "field_rel_l2/in_horizon/median", "field_rel_l2/in_horizon/max",
                                           "field_rel_l2/all/median", "field_rel_l2/extrapolation/median",
                                           "projection_rel_l2/in_horizon/median", "energy_rel_err/median",
                                           "energy_drift/max", "vpt/median")}
    long = long_horizon_energy(model, split.states[:4, 0], split.fine_points, float(times[1] - times[0]), 1000,
                               MIDPOINT)
    result["ours"].update(long)
    # full-order model: largest stable step that meets the target against the ground truth, in the horizon
    states0 = split.states[:, 0]
    cfl = scene.time_step / scene.cfl_fraction
    fom = []
    for frac in (0.5, 0.6, 0.7, 0.8, 0.9):
        try:
            seconds, states = timed(lambda: scene.simulate(states0, times[in_h], time_step=frac * cfl), repeats=1)
        except RuntimeError:
            fom.append({"cfl_fraction": frac, "stable": False})
            continue
        u = states[..., :2 * scene.n_nodes]
        ref = split.states[:, in_h, :2 * scene.n_nodes]
        err = float(np.median(np.sqrt(((u - ref) ** 2).sum((1, 2)) / np.maximum((ref**2).sum((1, 2)), 1e-300))))
        fom.append({"cfl_fraction": frac, "stable": True, "seconds": seconds, "nodal_rel_l2": err})
        print("FOM", fom[-1], flush=True)
    ok = [r for r in fom if r.get("stable") and r["nodal_rel_l2"] <= target]
    fom_best = ok[-1] if ok else None
    # reduced model: largest sample step (rollout step) that meets the target
    rom = []
    for stride in (1, 2, 4):
        ev = evaluate(model, split, stride=stride)
        rom.append({"dt": float(times[stride] - times[0]), "field_rel_l2/in_horizon/median":
                    float(ev.metrics["field_rel_l2/in_horizon/median"]),
                    "diverged_fraction": float(ev.metrics["diverged_fraction"])})
        print("ROM", rom[-1], flush=True)
    rom_ok = [r for r in rom if r["field_rel_l2/in_horizon/median"] <= target and r["diverged_fraction"] == 0]
    rom_best = rom_ok[-1] if rom_ok else rom[0]
    # the speed-up, measured back to back: the same trajectories over the training horizon
    pts = torch.as_tensor(split.fine_points, dtype=model.reference_tensor().dtype)
    q0 = model.reduce(pts[::4], torch.as_tensor(split.fields[:, 0, ::4], dtype=pts.dtype))
    v0 = model.project_velocity(q0, pts[::4], torch.as_tensor(split.velocities[:, 0, ::4], dtype=pts.dtype))
    steps = int(round(times[in_h][-1] / rom_best["dt"]))
    controls = trajectory_controls(scene, states0, q0)
    roll = lambda n: model.rollout(q0, v0, dt=rom_best["dt"], steps=n, integrator=MIDPOINT,  # noqa: E731
                                   on_divergence="mark", controls=controls)
    tabulation = model.tabulation
    timings = {}
    for name, spec in [("tabulated", tabulation), ("exact", None)] if tabulation is not None else [("exact", None)]:
        model.set_tabulation(spec)
        roll(2)  # warm-up (and the table, built once per model: its cost is reported apart)
        timings[name], _ = timed(lambda: roll(steps))
    model.set_tabulation(tabulation)
    rom_seconds = timings["tabulated" if tabulation is not None else "exact"]
    fom_frac = fom_best["cfl_fraction"] if fom_best else 0.5
    fom_seconds, _ = timed(lambda: scene.simulate(states0, times[in_h], time_step=fom_frac * cfl))
    result.update(fom=fom, rom=rom, fom_cfl_fraction=fom_frac, rom_dt=rom_best["dt"], rom_seconds=rom_seconds,
                  rom_seconds_exact=timings["exact"], speedup_exact=fom_seconds / timings["exact"],
                  dynamics="tabulated" if tabulation is not None else "lagrangian",
                  fom_seconds=fom_seconds, speedup=fom_seconds / rom_seconds, trajectories=len(states0),
                  horizon_s=float(times[in_h][-1]), fom_nodes=scene.n_nodes, fom_mesh=scene.mesh_shape)
    if tabulation is not None:
        result["table"] = {k: v for k, v in model.dynamics().info.items() if not isinstance(v, list)}
    e, horizon = base.energies, float(times[split.train_times])
    title = f"test trajectories, implicit midpoint, dt = {times[1] - times[0]:g} s"
    _ours_against_fem(times, (e["kinetic_pred"] + e["potential_pred"]) / scene.energy_scale,
                      (e["kinetic_true"] + e["potential_true"]) / scene.energy_scale, "energy / E_scale", title,
                      out / "energy.png", horizon)
    _tip_figure(base, out / "tip.png", title, horizon)
    return result


def elastic_actuated(model: Any, dm: SnapshotDataModule, out: Path) -> dict[str, Any]:
    scene, split = model.scene, dm.split("test")
    base = evaluate(model, split)
    times = split.times
    # damping: free decay (no load) from the test initial shapes
    u0, v0, load = scene.unpack(split.states[:, 0])
    free = scene.pack(u0, v0, np.zeros_like(load))
    decay = evaluate(model, split, states=scene.simulate(free, times))
    e = decay.energies
    pred = e["kinetic_pred"] + e["potential_pred"]
    true = e["kinetic_true"] + e["potential_true"]
    # a load outside the training range: frequency 1.2 Hz (training 0.3–0.7 Hz), amplitude 0.5
    unseen_load = np.tile([[0.5, 1.2]], (len(load), 1))
    unseen = evaluate(model, split, states=scene.simulate(scene.pack(u0, v0, unseen_load), times))
    _ours_against_fem(times, pred / scene.energy_scale, true / scene.energy_scale, "energy / E_scale",
                      f"free decay, α = {scene.damping} 1/s", out / "decay.png")
    _tip_figure(unseen, out / "tip_unseen_load.png",
                f"a 1.2 Hz load not seen in training (0.3–0.7 Hz), dt = {times[1] - times[0]:g} s",
                horizon=float(times[split.train_times]))
    rise = np.max(np.diff(pred, axis=1), axis=1) / scene.energy_scale
    keys = ("field_rel_l2/all/median", "field_rel_l2/all/max", "field_rel_l2/in_horizon/median",
            "field_rel_l2/extrapolation/median", "energy_rel_err/median", "diverged_fraction")
    return {"test": pick(base.metrics, *keys), "unseen_load": {"amplitude": 0.5, "frequency_hz": 1.2,
                                                                 **pick(unseen.metrics, *keys)},
            "free_decay": {**pick(decay.metrics, *keys),
                           "energy_ratio_end_over_start_ours_median": float(np.median(pred[:, -1] / pred[:, 0])),
                           "energy_ratio_end_over_start_fem_median": float(np.median(true[:, -1] / true[:, 0])),
                           "largest_energy_rise_per_sample_over_scale": float(np.max(rise))}}


# The reports of the built-in experiments, by experiment name (conf/experiment/<name>.yaml). Each report is
# specific to its scene by nature (a double pendulum's vpt, the bump's mode count, a cantilever's tip), so this
# table, unlike the studies (studylib.py and the studies built on it, which ask the scene object), is keyed by name.
# A report takes (model, datamodule, out folder) and any of the keyword options of main() below by name.
SCENES: dict[str, Callable[..., dict[str, Any]]] = {"double_pendulum": double_pendulum, "bump": bump,
                                                    "elastic": elastic, "elastic_actuated": elastic_actuated}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", required=True, choices=sorted(SCENES))
    parser.add_argument("--ckpt", default=None, help="default: outputs/issue4/<scene>/checkpoints/last.ckpt")
    parser.add_argument("--out", default=None, help="default: outputs/scenes/<scene>")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--dynamics", choices=["checkpoint", "lagrangian", "tabulated"], default="checkpoint",
                        help="our rollouts: as the checkpoint was trained, the exact pullback, or the tabulated one "
                             "(elastic also times the exact one for comparison)")
    parser.add_argument("--max-modes", type=int, default=12, help="bump: POD modes k = 1 … this")
    parser.add_argument("--bb-iterations", type=int, default=2000,
                        help="double_pendulum: training iterations of the black box's latent MLP")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    ckpt = Path(args.ckpt or ROOT / "outputs" / "issue4" / args.scene / "checkpoints" / "last.ckpt")
    if not ckpt.exists():
        raise SystemExit(f"no checkpoint at {ckpt}; train first: python -m lnf.train +experiment={args.scene} "
                         f"hydra.run.dir=outputs/issue4/{args.scene}")
    out = Path(args.out or ROOT / "outputs" / "scenes" / args.scene)
    out.mkdir(parents=True, exist_ok=True)
    model = load(ckpt)
    model.eval()
    start = time.perf_counter()
    report = SCENES[args.scene]
    options = {"max_modes": args.max_modes, "bb_iterations": args.bb_iterations}
    extra = {k: v for k, v in options.items() if k in inspect.signature(report).parameters}  # the ones it takes
    dm = datamodule_of(model)
    if args.dynamics != "checkpoint" and hasattr(model, "set_tabulation"):
        model.set_tabulation((model.tabulation or {}) if args.dynamics == "tabulated" else None)
    if getattr(model, "tabulation", None) is not None:
        ensure_code_range(model, Path(dm.path), model.scene, dm.config)
    result = report(model, dm, out, **extra)
    result["dynamics"] = "tabulated" if getattr(model, "tabulation", None) is not None else "lagrangian"
    result["seconds"] = time.perf_counter() - start
    result["checkpoint"] = str(ckpt)
    result["machine"] = {"platform": platform.platform(), "processor": platform.processor(),
                         "torch": torch.__version__, "threads": torch.get_num_threads()}
    write_json_atomic(out / "results.json", result)
    print(json.dumps(result, indent=1, default=str))
    return result


if __name__ == "__main__":
    main()
