"""The measurements of ``python -m experiments.scenes`` (:mod:`experiments.scenes` says which a scene can have and
runs them): each takes the :class:`Context` of one trained checkpoint and returns its part of ``results.json``."""

import argparse
import copy
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import torch
from omegaconf import OmegaConf

from experiments import scene_figures as figures, studylib
from lnf.baselines.latent_mlp import LatentMLPDynamics
from lnf.baselines.pod import PODGalerkin
from lnf.evaluation import trajectory_controls
from lnf.evaluation_pipeline import (EvaluationData, EvaluationSpec, checkpoint_data, evaluate_model,
                                     split_long_check)
from lnf.train import fit_latent_dynamics
from lnf.dataset.snapshots import SnapshotData, checkpoint_snapshot_data

ROOT = Path(__file__).resolve().parents[1]


def snapshot_data_of(model: Any) -> SnapshotData:
    """The checkpoint's own dataset (generated if missing), found as lnf.evaluate finds it
    (:func:`lnf.evaluation_pipeline.checkpoint_data`): a data path outside the data folder is only read."""
    data_dir = Path(os.environ.get("LNF_DATA_DIR") or Path(os.environ.get("LNF_ROOT", ROOT)) / "data")
    return checkpoint_snapshot_data(model, checkpoint_data(model, data_dir.resolve())[0])


def evaluate(model: Any, split: Any, integrator: Any, states: np.ndarray | None = None, stride: int = 1) -> Any:
    """Roll out the split (or `states`, re-simulated ground truth: the scene's fields, energies and loads of them) on
    the stored fine grid with `integrator`; `stride` subsamples time."""
    data = EvaluationData.of_split(split, model.scene, stride=stride)
    if states is not None:
        data = replace(data, states=states[:, ::stride], true_fields=None, true_velocities=None, true_energies=None,
                       controls=None)
    return evaluate_model(model, data, EvaluationSpec(integrator=integrator, label="rollout")).rollouts


def experiment_integrator_order(scene: str, config_dir: Path | None) -> int:
    """The order of the implicit midpoint rule that `python -m lnf.train +experiment=<scene>` rolls out with, from
    the config it composes (:meth:`studylib.Study.composed`; the checkpoint does not record it); for a scene with no
    experiment of that name, conf/integrator/implicit_midpoint.yaml's. The double pendulum and the bump set 2, the
    elastic scenes 4."""
    try:
        studylib.experiment_file(scene, config_dir)
    except FileNotFoundError:
        return int(OmegaConf.load(studylib.config_file("integrator/implicit_midpoint", config_dir)).get("order", 2))
    study = studylib.Study(name="scenes", scene=scene, mode="reduced", out=ROOT, threads=1, config_dir=config_dir)
    return int(study.composed().integrator.get("order", 2))


def pick(metrics: dict[str, float], *keys: str) -> dict[str, float]:
    """The `keys` of `metrics` that it has, as floats."""
    return {k: float(metrics[k]) for k in keys if k in metrics}


def timed(fn: Callable[[], Any], repeats: int = 2) -> tuple[float, Any]:
    """(the fastest wall-clock of `repeats` calls [s], the last call's result)."""
    best, result = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return best, result


class Skipped(Exception):
    """A measurement that cannot run on this scene or checkpoint; the message says why."""


@dataclass
class Context:
    """What every measurement gets: the model, its dataset, the test split and our rollout of it, the output folder
    and the command line's options."""

    model: Any
    dm: SnapshotData
    out: Path
    options: argparse.Namespace
    integrator: dict  # the structure-preserving rule of our rollouts: {"name": "implicit_midpoint", "order": 2|4}
    split: Any = field(init=False)
    base: Any = field(init=False)

    def __post_init__(self) -> None:
        self.split = self.dm.split("test")
        self.base = evaluate(self.model, self.split, self.integrator)

    @property
    def scene(self) -> Any:
        return self.model.scene


# ---------------------------------------------------------------------------------------------------------
def black_box(ctx: Context) -> dict[str, Any]:
    """vpt and the 20×-horizon energy drift of ours against the black-box latent MLP on the same embedding."""
    model, split, ours = ctx.model, ctx.split, ctx.base
    if not hasattr(model, "latent_dynamics"):
        raise Skipped(f"the checkpoint is a {type(model).__name__}, not our model: it has no embedding to fit a "
                      "black box to")
    black = copy.deepcopy(model)
    black.latent_dynamics = LatentMLPDynamics(latent_dim=model.latent_dim, iterations=ctx.options.bb_iterations)
    fit = fit_latent_dynamics(black, ctx.dm)
    bb = evaluate(black, split, "rk4")
    dt = float(split.times[1] - split.times[0])
    horizon = float(split.times[split.train_times])
    steps = int(round(20 * horizon / dt))
    # the first 8 test trajectories, 20x the horizon (1000 steps each)
    drift_ours = split_long_check(model, split, 8, steps, ctx.integrator)
    drift_bb = split_long_check(black, split, 8, steps, "rk4")
    keys = ("vpt/median", "vpt/min", "field_rel_l2/in_horizon/median", "field_rel_l2/all/median",
            "projection_rel_l2/all/median", "energy_rel_err/median", "diverged_fraction")
    result = {"ours": {**pick(ours.metrics, *keys), **drift_ours}, "black_box": {**pick(bb.metrics, *keys), **drift_bb},
              "black_box_fit": fit, "long_steps": steps, "long_horizon_s": steps * dt}
    result["drift_ratio_median"] = drift_bb["energy_drift_long/median"] / max(drift_ours["energy_drift_long/median"], 1e-300)
    figures.vpt_histogram(ours, bb, horizon, ctx.out / "vpt.png")
    return result


# ---------------------------------------------------------------------------------------------------------
def modes(ctx: Context) -> dict[str, Any]:
    """The test error of POD-Galerkin with k = 1 … --max-modes modes and of the best linear k-mode projection,
    against ours; the k that match our error."""
    model, dm, split, ours = ctx.model, ctx.dm, ctx.split, ctx.base
    max_modes = ctx.options.max_modes
    points, values, _ = (torch.as_tensor(a, dtype=torch.float64) for a in dm.observations("train"))
    pod_rows = []
    for k in range(1, max_modes + 1):
        pod = PODGalerkin(model.scene, latent_dim=k, degree=24).double()
        pod.fit_to_observations(points, values)
        metrics = evaluate(pod, split, ctx.integrator).metrics
        pod_rows.append({"k": k, **pick(metrics, "field_rel_l2/all/median", "projection_rel_l2/all/median",
                                        "diverged_fraction")})
        print(f"POD k={k}: {pod_rows[-1]}", flush=True)
    # the best any k-mode linear model can do: SVD of the full fine-grid training fields (every component),
    # projection of the test fields
    train = dm.split("train")
    n_values = train.fields.shape[2] * train.fields.shape[3]  # points × components
    X = train.fields[:, :train.train_times].reshape(-1, n_values).astype(np.float64)
    mean = X.mean(0)
    _, _, Vt = np.linalg.svd(X - mean, full_matrices=False)
    Y = split.fields.reshape(*split.fields.shape[:2], n_values).astype(np.float64)
    oracle = []
    for k in range(1, max_modes + 1):
        R = mean + ((Y - mean) @ Vt[:k].T) @ Vt[:k]
        oracle.append(float(np.median(np.sqrt(((R - Y) ** 2).sum((1, 2)) / (Y**2).sum((1, 2))))))
    ours_err = float(ours.metrics["field_rel_l2/all/median"])
    needed = next((r["k"] for r in pod_rows if r["field_rel_l2/all/median"] <= ours_err), None)
    needed_oracle = next((k + 1 for k, e in enumerate(oracle) if e <= ours_err), None)
    figures.modes_figure(pod_rows, oracle, int(model.latent_dim), ours_err, ctx.out / "modes.png")
    return {"ours": pick(ours.metrics, "field_rel_l2/all/median", "field_rel_l2/in_horizon/median",
                         "field_rel_l2/extrapolation/median", "projection_rel_l2/all/median", "energy_rel_err/median"),
            "pod": pod_rows, "oracle_projection": oracle, "pod_modes_to_match_ours": needed,
            "oracle_modes_to_match_ours": needed_oracle}


# ---------------------------------------------------------------------------------------------------------
REFERENCE_STEP_FACTORS = (1.0, 1.2, 1.4, 1.6, 1.8)  # × the scene's own time_step (0.5 … 0.9 of a CFL limit at 0.5)


def reference_steps(scene: Any) -> list[Optional[float]]:
    """The time steps at which to try the full-order reference: multiples of its own ``time_step`` where its
    ``simulate`` takes a ``time_step`` argument, else [None] (its own step only)."""
    import inspect

    own = getattr(scene, "time_step", None)
    if "time_step" in inspect.signature(scene.simulate).parameters and isinstance(own, (int, float)) and own > 0:
        return [f * float(own) for f in REFERENCE_STEP_FACTORS]
    return [None]


def _simulate(scene: Any, states0: np.ndarray, times: np.ndarray, time_step: Optional[float]) -> np.ndarray:
    return scene.simulate(states0, times) if time_step is None else scene.simulate(states0, times, time_step=time_step)


def speedup(ctx: Context) -> dict[str, Any]:
    """Accuracy, energy and the speed-up of our rollout over the scene's (expensive) full-order reference."""
    model, split, base, target = ctx.model, ctx.split, ctx.base, ctx.options.target
    scene = model.scene
    times = split.times
    in_h = times < times[split.train_times]
    result: dict[str, Any] = {"ours": pick(base.metrics, "field_rel_l2/in_horizon/median", "field_rel_l2/in_horizon/max",
                                           "field_rel_l2/all/median", "field_rel_l2/extrapolation/median",
                                           "projection_rel_l2/in_horizon/median", "energy_rel_err/median",
                                           "energy_drift/max", "vpt/median")}
    long = split_long_check(model, split, 4, 1000, ctx.integrator)
    result["ours"].update(long)
    # full-order reference: the largest step that meets the target against the stored ground truth, in the horizon
    states0 = split.states[:, 0]
    ref = split.fields[:, in_h].astype(np.float64)
    fom = []
    for step in reference_steps(scene):
        factor = None if step is None else step / float(scene.time_step)
        try:
            seconds, states = timed(lambda: _simulate(scene, states0, times[in_h], step), repeats=1)
        except RuntimeError:
            fom.append({"step_factor": factor, "time_step": step, "stable": False})
            continue
        q = np.asarray(scene.fields(states, split.fine_points)[0], dtype=np.float64)
        err = float(np.median(np.sqrt(((q - ref) ** 2).sum((1, 2, 3)) / np.maximum((ref**2).sum((1, 2, 3)), 1e-300))))
        fom.append({"step_factor": factor, "time_step": step, "stable": True, "seconds": seconds, "field_rel_l2": err})
        print("FOM", fom[-1], flush=True)
    ok = [r for r in fom if r.get("stable") and r["field_rel_l2"] <= target]
    fom_best = ok[-1] if ok else None
    # reduced model: largest sample step (rollout step) that meets the target
    rom = []
    for stride in (1, 2, 4):
        ev = base if stride == 1 else evaluate(model, split, ctx.integrator, stride=stride)
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
    roll = lambda n: model.rollout(q0, v0, dt=rom_best["dt"], steps=n, integrator=ctx.integrator,  # noqa: E731
                                   on_divergence="mark", controls=controls)
    tabulation = getattr(model, "tabulation", None)
    timings = {}
    for name, spec in [("tabulated", tabulation), ("exact", None)] if tabulation is not None else [("exact", None)]:
        if hasattr(model, "set_tabulation"):
            model.set_tabulation(spec)
        roll(2)  # warm-up (and the table, built once per model: its cost is reported apart)
        timings[name], _ = timed(lambda: roll(steps))
    if hasattr(model, "set_tabulation"):
        model.set_tabulation(tabulation)
    rom_seconds = timings["tabulated" if tabulation is not None else "exact"]
    # with decoding: the rollout, then every stored frame decoded (exactly) on the evaluation points
    stride = max(1, int(round(float(times[1] - times[0]) / rom_best["dt"])))
    fine = torch.as_tensor(split.fine_points, dtype=pts.dtype)

    def roll_and_decode() -> Any:
        codes = roll(steps).q[:, ::stride]  # (B, T', d) at the stored times
        with torch.no_grad():
            return model.decode(codes.reshape(-1, codes.shape[-1]), fine)

    decoded_seconds, _ = timed(roll_and_decode)
    fom_step = fom_best["time_step"] if fom_best else reference_steps(scene)[0]
    fom_seconds, _ = timed(lambda: _simulate(scene, states0, times[in_h], fom_step))
    result.update(fom=fom, rom=rom, fom_time_step=fom_step,
                  fom_step_factor=None if fom_step is None else fom_step / float(scene.time_step),
                  rom_dt=rom_best["dt"], rom_seconds=rom_seconds,
                  rom_seconds_exact=timings["exact"], speedup_exact=fom_seconds / timings["exact"],
                  dynamics="tabulated" if tabulation is not None else "lagrangian",
                  fom_seconds=fom_seconds, speedup=fom_seconds / rom_seconds, trajectories=len(states0),
                  rom_seconds_with_decoding=decoded_seconds, speedup_with_decoding=fom_seconds / decoded_seconds,
                  decoding_points=int(len(fine)),
                  horizon_s=float(times[in_h][-1]), fom_state_size=int(states0.shape[-1]))
    if tabulation is not None:
        result["table"] = {k: v for k, v in model.dynamics().info.items() if not isinstance(v, list)}
    horizon = float(times[split.train_times])
    title = f"test trajectories, implicit midpoint, dt = {times[1] - times[0]:g} s"
    if "kinetic_true" in base.energies:  # a scene without reference energies has no energy figure
        figures.energy_figure(base, scene.energy_scale, title, ctx.out / "energy.png", horizon)
    figures.probe_figure(base, ctx.out / "tip.png", title, horizon)
    return result


# ---------------------------------------------------------------------------------------------------------
def with_controls(scene: Any, states: np.ndarray, controls: np.ndarray) -> np.ndarray:
    """Full-order states (n, S) with the load parameters `controls` (n, c) instead of their own: the scene's
    ``with_controls(states, controls)`` if it defines one, else the last c entries of the state replaced, where that
    is where ``Scene.controls`` reads them from. Checked: ``scene.controls`` of the result is `controls`."""
    states, controls = np.asarray(states, dtype=np.float64), np.asarray(controls, dtype=np.float64)
    if hasattr(scene, "with_controls"):
        out = np.asarray(scene.with_controls(states, controls))
    else:
        own, c = scene.controls(states), controls.shape[-1]
        if own is None or np.shape(own)[-1] != c or not np.array_equal(np.asarray(own), states[..., -c:]):
            raise Skipped(f"scene {scene.name!r} has no with_controls(states, controls) and does not keep its "
                          f"{c} load parameters as the last entries of its state: define with_controls to set loads")
        out = states.copy()
        out[..., -c:] = controls
    if not np.allclose(scene.controls(out), controls):
        raise Skipped(f"scene {scene.name!r}: the states with other loads do not carry them (controls() of the "
                      f"result is not what was set)")
    return out


def unseen_load(training: np.ndarray, given: Optional[list[float]]) -> np.ndarray:
    """A load (c,) not seen in training: `given` (--unseen-load), else each parameter beyond the training
    trajectories' range [lo, hi] by half its width (hi + (hi − lo)/2; twice hi where the range is a point)."""
    lo, hi = training.min(0), training.max(0)
    if given is not None:
        if len(given) != len(hi):
            raise SystemExit(f"--unseen-load: the scene's loads have {len(hi)} parameters, got {len(given)} values")
        return np.asarray(given, dtype=np.float64)
    return np.where(hi > lo, hi + 0.5 * (hi - lo), 2.0 * hi)


LOAD_KEYS = ("field_rel_l2/all/median", "field_rel_l2/all/max", "field_rel_l2/in_horizon/median",
             "field_rel_l2/extrapolation/median", "energy_rel_err/median", "diverged_fraction")


def loads(ctx: Context) -> dict[str, Any]:
    """The test loads and one load not seen in training, each against the re-simulated reference."""
    scene, split, base, model = ctx.scene, ctx.split, ctx.base, ctx.model
    times = split.times
    states0 = split.states[:, 0]
    training = np.asarray(scene.controls(ctx.dm.split("train").states[:, 0]), dtype=np.float64)
    load = unseen_load(training, ctx.options.unseen_load)
    unseen_states = with_controls(scene, states0, np.tile(load, (len(states0), 1)))
    unseen = evaluate(model, split, ctx.integrator, states=scene.simulate(unseen_states, times))
    text = ", ".join(f"{x:.3g}" for x in load)
    ranges = ", ".join(f"{a:.3g}…{b:.3g}" for a, b in zip(training.min(0), training.max(0)))
    figures.probe_figure(unseen, ctx.out / "tip_unseen_load.png",
                         f"a load not seen in training ({text}; training {ranges}), dt = {times[1] - times[0]:g} s",
                         horizon=float(times[split.train_times]))
    return {"test": pick(base.metrics, *LOAD_KEYS),
            "unseen_load": {"controls": load.tolist(), "training_range": [[float(a), float(b)] for a, b in
                                                                          zip(training.min(0), training.max(0))],
                            **pick(unseen.metrics, *LOAD_KEYS)}}


def _largest_rise(energy: np.ndarray, scale: float) -> float:
    """The largest rise of an energy (n, T) between consecutive samples, over `scale`."""
    return float(np.max(np.diff(energy, axis=1))) / scale


def decay(ctx: Context) -> dict[str, Any]:
    """The free decay of the test initial states (their loads removed): does the reduced energy decay?"""
    scene, split, model = ctx.scene, ctx.split, ctx.model
    times = split.times
    states0 = split.states[:, 0]
    free = with_controls(scene, states0, np.zeros_like(scene.controls(states0))) if scene.has_controls else states0
    ev = evaluate(model, split, ctx.integrator, states=scene.simulate(free, times))
    pred, true = figures.energy_figure(ev, scene.energy_scale, "free decay (no load)", ctx.out / "decay.png")
    return {"free_decay": {**pick(ev.metrics, *LOAD_KEYS),
                           "energy_ratio_end_over_start_ours_median": float(np.median(pred[:, -1] / pred[:, 0])),
                           "energy_ratio_end_over_start_fem_median": float(np.median(true[:, -1] / true[:, 0])),
                           "largest_energy_rise_per_sample_over_scale": _largest_rise(pred, scene.energy_scale)}}


def damped(ctx: Context) -> dict[str, Any]:
    """The test initial states under mass-proportional damping: the dissipated energy, ours against the reference."""
    rate = float(ctx.options.damping)
    scene = ctx.scene.with_damping(rate)
    model = copy.deepcopy(ctx.model)
    model.scene = scene
    if hasattr(model, "set_tabulation"):
        model.set_tabulation(None)
    split, times = ctx.split, ctx.split.times
    ev = evaluate(model, split, ctx.integrator, states=scene.simulate(split.states[:, 0], times))
    horizon = float(times[split.train_times])
    pred, true = figures.energy_figure(ev, scene.energy_scale, f"damped, α = {rate:g} 1/s (trained undamped)",
                                       ctx.out / "damped.png", horizon)
    figures.probe_figure(ev, ctx.out / "damped_tip.png", f"damped, α = {rate:g} 1/s (trained undamped), dt = "
                         f"{times[1] - times[0]:g} s", horizon=horizon)
    lost_ours, lost_true = pred[:, 0] - pred[:, -1], true[:, 0] - true[:, -1]
    return {"damped": {"damping_per_second": rate, **pick(ev.metrics, *LOAD_KEYS),
                       "dissipated_ratio_ours_over_reference_median": float(np.median(lost_ours / lost_true)),
                       "energy_error_max_over_scale": float(np.max(np.abs(pred - true)) / scene.energy_scale),
                       "largest_energy_rise_per_sample_over_scale": _largest_rise(pred, scene.energy_scale)}}


def shape(ctx: Context) -> dict[str, Any]:
    """The deformed body in 3-D, ours against the reference, at four times of the first test trajectory
    (``shape.png``: the evaluation points moved to X + u, coloured by the displacement's size, the reference's
    beside ours, two times before the training horizon and two after)."""
    picks = figures.shape_figure(ctx.base, float(ctx.split.times[ctx.split.train_times]), ctx.out / "shape.png")
    return {"shape_figure": "shape.png", "shape_times_s": [float(ctx.base.times[k]) for k in picks]}
