"""The settings of ``python -m lnf.evaluate`` (conf/evaluate.yaml): checked before anything is loaded, priced
before anything is simulated (:func:`check_budget`), and turned into the data and spec that
:func:`lnf.evaluation_pipeline.evaluate_model` takes (:func:`rollout_request`)."""
from __future__ import annotations

import logging
import math
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
from omegaconf import DictConfig, OmegaConf

from lnf.config_keys import check_known_keys
from lnf.dataset import GROUND_TRUTH_FOLDER, SOURCE_ARRAYS, SPLITS, simulated_ground_truth
from lnf.decoding_table import check_decoding
from lnf.dynamics_kind import dynamics_kind
from lnf.evaluation_cost import (MEMORY_ENV, EvaluationCost, evaluation_cost, memory_limit, quadrature_size,
                                 size_text)
from lnf.evaluation_pipeline import EvaluationData, EvaluationSpec
from lnf.model import build
from lnf.quadrature import grid_shape_of, midpoint_grid
from lnf.trajectories import TIME_TOLERANCE
from lnf.trust import trusted_modules
from lnf.utils import EVALUATION_RULES, check_numbers, is_number, number_problem

log = logging.getLogger("lnf.evaluate")
GRID_KINDS = ("stored", "uniform", "random")
#: the numbers of conf/evaluate.yaml: (kind, low, high, what, unit, what null means), see lnf.utils.number_problem;
#: the settings it shares with ``evaluation:`` of conf/train.yaml are lnf.utils.EVALUATION_RULES
EVALUATE_RULES: dict[str, tuple] = {
    "dt": (">", 0, None, "the sample spacing of the evaluation", "s", "the data's"),
    "horizon": (">", 0, None, "how long to roll out", "s", "the data's horizon"),
    "train_horizon": (">", 0, None, "where extrapolation starts; 0 leaves no time before it", "s",
                      "the data's training horizon"),
    "max_trajectories": ("int", 1, None, "how many trajectories of the split to evaluate", "", "all of them"),
    **EVALUATION_RULES,
    "closure_degree": ("int", 2, 6, "the degree of a potential closure fitted on the training trajectories first", "",
                       "the checkpoint's own dynamics"),
    "closure_max_terms": ("int", 1, None, "the most terms of a closure fitted first (its degree is lowered to fit)", "",
                          "no cap"),
    "threads": ("int", 1, None, "torch CPU threads", "", "torch's default"),
    "grid.resolution": ("int", 1, None, "points per axis of grid.kind=uniform; below 1 the grid has no points"),
    "grid.n_points": ("int", 1, None, "points of grid.kind=random; below 1 the grid has no points"),
    "grid.seed": ("int", 0, None, "the seed of grid.kind=random"),
    "max_memory_gb": (">", 0, None, "the memory the evaluation may hold", "GB",
                      f"the memory available now, or ${MEMORY_ENV}"),
    "max_steps": ("int", 1, None, "the most integration steps of one rollout, the time budget", "", "no limit"),
}


def _shown(value: Any) -> str:
    """A setting as it would be typed: null, 1e+09, 0.05, 64."""
    if value is None:
        return "null"
    return f"{value:g}" if is_number(value) else str(value)


def _span(cfg: DictConfig, dt: Optional[float], horizon: Optional[float]) -> str:
    """"horizon=… at dt=…" as set, each null one with the data's value where known: what a refusal names."""
    def shown(key: str, value: Optional[float]) -> str:
        data = f" (the data’s: {value:g} s)" if cfg.get(key) is None and value else " [s]"
        return f"{key}={_shown(cfg.get(key))}{data}"

    return f"{shown('horizon', horizon)} at {shown('dt', dt)}"


def rollout_frames(cfg: DictConfig, dt: float, horizon: float) -> int:
    """The frames of a rollout over `horizon` [s] sampled every `dt` [s] (t = 0, dt, …, horizon − dt; either may be
    the data's where `cfg` leaves it null): horizon/dt, which must be a whole number (to 1e-9, relative; to
    :data:`lnf.trajectories.TIME_TOLERANCE` where one is the data's) and ≥ 2, or
    a ValueError names both and the horizons that work. An explicit train_horizon beyond the horizon is refused
    too: nothing would come after it."""
    span = _span(cfg, dt, horizon)
    ratio = horizon / dt
    frames = int(round(ratio))
    # a data's times are uniform to TIME_TOLERANCE (a user's arrays); two settings, to rounding
    tol = 1e-9 if cfg.get("horizon") is not None and cfg.get("dt") is not None else TIME_TOLERANCE
    if abs(ratio - frames) > tol * max(frames, 1):
        works = [f"horizon={k * dt:.12g}" for k in (math.floor(ratio), math.ceil(ratio)) if k >= 2]
        raise ValueError(f"{span} is {ratio:.6g} steps of dt, not a whole number: the rollout samples t = 0, dt, …, "
                         f"horizon − dt and would cover {frames * dt:g} s instead of {horizon:g} s; set "
                         f"{' or '.join(works)} (a whole number of dt), or a dt that divides the horizon")
    if frames < 2:
        raise ValueError(f"{span} is {frames} frame{'' if frames == 1 else 's'}: a rollout needs at least 2 frames "
                         f"(t = 0 and dt), i.e. horizon ≥ 2·dt = {2 * dt:g} s")
    train_horizon = cfg.get("train_horizon")
    if train_horizon is not None and train_horizon > horizon * (1 + 1e-9):
        raise ValueError(f"train_horizon={_shown(train_horizon)} [s] (where extrapolation starts) is beyond the "
                         f"evaluated {span}: no frame would come after it; set train_horizon ≤ {horizon:g}, or null "
                         f"(the data's training horizon)")
    return frames


def check_settings(cfg: DictConfig) -> None:
    """Refuse keys lnf.evaluate does not use and settings it cannot run, before anything is loaded or rolled out."""
    check_known_keys(cfg, "evaluate", "lnf.evaluate")
    if OmegaConf.is_missing(cfg, "ckpt_path") or cfg.get("ckpt_path") in (None, ""):
        raise ValueError("ckpt_path is required: the checkpoint to evaluate, e.g. "
                         "ckpt_path=outputs/pendulum/runs/<date>/checkpoints/last.ckpt")
    trusted_modules(trust_setting(cfg))  # a bad module name is refused here, naming it
    if cfg.get("split") not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {cfg.get('split')!r}")
    problems = (number_problem(key, OmegaConf.select(cfg, key), rule) for key, rule in EVALUATE_RULES.items())
    problem = next((p for p in problems if p), None)
    if problem:
        raise ValueError(problem)
    if cfg.get("dt") is not None and cfg.get("horizon") is not None:
        rollout_frames(cfg, float(cfg.dt), float(cfg.horizon))  # a whole number ≥ 2 of dt, before anything is loaded
    check_decoding(cfg.get("decoding", "auto"))
    kind = OmegaConf.select(cfg, "grid.kind", default="stored")
    if kind not in GRID_KINDS:
        raise ValueError(f"grid.kind must be 'stored', 'uniform' or 'random', got {kind!r}")
    check_numbers(cfg)  # every other number (integrator.tol, quadrature.*, dynamics.*, initial_states): finite, in range


def trust_setting(cfg: DictConfig) -> list[str]:
    """``trust=`` as a list of module names: ``trust=mypkg`` (one name) or ``trust=[mypkg, other]``."""
    value = cfg.get("trust")
    if value is None or isinstance(value, str):
        return [value] if value else []
    if OmegaConf.is_list(value):
        return [str(v) for v in value]
    raise ValueError(f"trust must be a module name or a list of them (trust=[mypkg]), got {value!r}")


def evaluation_points(grid: DictConfig, bounds: list[list[float]], stored: np.ndarray) -> tuple[np.ndarray, Optional[tuple]]:
    """Points (N, dim_B) of the evaluation grid and its shape (None for scattered points)."""
    kind = grid.get("kind", "stored")
    dim = len(bounds)
    if kind == "stored":
        return stored, grid_shape_of(stored, bounds)  # None: scattered points (mesh nodes, samples)
    if kind == "uniform":
        res = int(grid.resolution)
        if res < 1:
            raise ValueError(f"grid.resolution must be ≥ 1 (points per axis), got {res}: the grid has no points")
        return midpoint_grid(res, bounds).numpy(), (res,) * dim
    if kind == "random":
        n = int(grid.n_points)
        if n < 1:
            raise ValueError(f"grid.n_points must be ≥ 1, got {n}: the evaluation grid has no points")
        rng = np.random.default_rng(int(grid.get("seed", 0)))
        b = np.asarray(bounds)
        return (b[:, 0] + (b[:, 1] - b[:, 0]) * rng.random((n, dim))).astype(np.float32), None
    raise ValueError(f"grid.kind must be 'stored', 'uniform' or 'random', got {kind!r}")


def read_initial_states(spec: Any) -> np.ndarray:
    """Full-order initial states (n, state_dim) from a list of lists or from the path of a .npy file (a large state,
    such as the elastic scene's nodal displacements and velocities, does not fit on a command line)."""
    if isinstance(spec, (str, Path)):
        path = Path(spec)
        if path.suffix != ".npy" or not path.is_file():
            raise ValueError(f"initial_states={spec!r}: expected a list of states or an existing .npy file of shape "
                             f"(n, state_dim)")
        try:
            return np.asarray(np.load(path, allow_pickle=False), dtype=np.float64)
        except (ValueError, OSError) as err:
            raise ValueError(f"initial_states={spec!r}: not a readable .npy array of states ({err})") from err
    return np.asarray(OmegaConf.to_container(spec, resolve=True) if OmegaConf.is_config(spec) else spec,
                      dtype=np.float64)


def choose_dynamics(model: Any, spec: Any, ckpt_path: Any) -> None:
    """Apply ``dynamics=tabulated`` / ``dynamics=lagrangian`` to a loaded model (None keeps the checkpoint's)."""
    if not spec:
        return
    target = str(spec.get("_target_", ""))
    kind = dynamics_kind(spec)  # read before resolving: a learned dynamics' spec names training keys
    if not kind.trained:
        spec = OmegaConf.to_container(spec, resolve=True) if OmegaConf.is_config(spec) else dict(spec)
    if not hasattr(model, "set_tabulation") or getattr(model, "latent_dynamics", None) is not None:
        raise ValueError(f"dynamics={target.rpartition('.')[2] or spec} applies to our model's pulled-back Lagrangian; "
                         f"the checkpoint {ckpt_path} holds a {type(model).__name__} with its own dynamics")
    if kind.trained:
        raise ValueError(f"dynamics: lnf.evaluate can switch between the exact and the tabulated pullback "
                         f"(dynamics=lagrangian, dynamics=tabulated), got _target_={target!r}, a {kind.name} dynamics "
                         f"(learned dynamics are trained)")
    model.set_tabulation(spec if kind.needs_codes else None)


def planned_cost(cfg: DictConfig, model: Any, data: dict[str, Any], split: Any = None
                 ) -> tuple[EvaluationCost, Optional[float], Optional[float]]:
    """What the evaluation asked for will cost, computed from sizes alone (nothing allocated): its
    :class:`EvaluationCost` (trajectories, frames, points, integration steps, memory) and the dt and horizon [s] it
    rolls out over (None where unknown). Before the data are loaded (`split` None) the sizes come from the settings
    and the checkpoint's record of its data, unknown ones counted as 1 (a lower bound); with `split`, from the data."""
    scene = model.scene
    dim = len(scene.bounds)
    generated = data.get("source") != SOURCE_ARRAYS
    record = data if generated else {}
    if cfg.get("initial_states") is not None:
        n = len(read_initial_states(cfg.initial_states))
    else:
        n = len(split) if split is not None else int(record.get(f"n_{cfg.split}") or 1)
        if cfg.get("max_trajectories") is not None:
            n = min(n, int(cfg.max_trajectories))
    if split is not None:
        data_dt, data_frames = float(split.times[1] - split.times[0]), len(split.times)
    else:
        data_dt = float(record["dt"]) if record.get("dt") else None
        data_frames = int(record["n_times"]) if record.get("n_times") else None
    dt = float(cfg.dt) if cfg.get("dt") is not None else data_dt
    horizon = float(cfg.horizon) if cfg.get("horizon") is not None else \
        (data_frames * data_dt if data_frames and data_dt else None)
    frames = rollout_frames(cfg, dt, horizon) if dt and horizon else (data_frames or 1)
    kind = OmegaConf.select(cfg, "grid.kind", default="stored")
    if kind == "uniform":
        points = int(cfg.grid.resolution) ** dim
    elif kind == "random":
        points = int(cfg.grid.n_points)
    elif split is not None:
        points = len(split.fine_points)
    else:
        points = int(record["fine_resolution"]) ** dim if record.get("fine_resolution") else 1
    state_dim = split.states.shape[-1] if split is not None else len(getattr(scene, "state_names", ()) or ())
    substeps = int(OmegaConf.select(cfg, "integrator.substeps", default=1) or 1)
    long_steps = int(cfg.get("long_steps") or 0)
    cost = evaluation_cost(max(n, 1), max(frames, 1), max(points, 1), scene.field_dim, keep_fields=int(cfg.figures),
                           substeps=substeps, state_dim=state_dim, latent_dim=model.latent_dim, body_dim=dim,
                           long_trajectories=min(int(cfg.long_trajectories), max(n, 1)) if long_steps > 0 else 0,
                           long_steps=long_steps)
    return cost, dt, horizon


def check_budget(cfg: DictConfig, cost: EvaluationCost, dt: Optional[float], horizon: Optional[float]) -> None:
    """Refuse, before anything is loaded, simulated or rolled out, an evaluation over the time budget (``max_steps``
    integration steps per rollout, integrator.substeps counted) or over the memory it may hold (:func:`memory_limit`),
    naming the setting, its value, the estimate, the limit and what to change."""
    k = cost.substeps
    max_steps = cfg.get("max_steps")
    span = _span(cfg, dt, horizon)
    if max_steps is not None and cost.rollout_steps > int(max_steps):
        raise ValueError(f"{span} is {cost.frames} frames: with integrator.substeps={k} the rollout takes "
                         f"{cost.rollout_steps:.4g} integration steps per trajectory, over max_steps={max_steps} (the "
                         f"time budget of lnf.evaluate): lower horizon, raise dt"
                         f"{', lower integrator.substeps' if k > 1 else ''}, or raise max_steps (null: no limit) if "
                         f"you mean to wait for it")
    if max_steps is not None and cost.long_rollout_steps > int(max_steps):
        raise ValueError(f"long_steps={_shown(cfg.long_steps)} with integrator.substeps={k} is "
                         f"{cost.long_rollout_steps:.4g} integration steps, over max_steps={max_steps} (the time "
                         f"budget of lnf.evaluate): lower long_steps (0 skips the long-horizon check)"
                         f"{' or integrator.substeps' if k > 1 else ''}, or raise max_steps (null: no limit) if you "
                         f"mean to wait for it")
    limit, where = memory_limit(cfg.get("max_memory_gb"))
    if limit is None:
        log.info("the memory the evaluation may use is not checked: %s (set max_memory_gb to check it)", where)
        return
    if cost.rollout_memory_bytes > limit:
        grid = {"uniform": f"grid.kind=uniform, grid.resolution={_shown(cfg.grid.resolution)}",
                "random": f"grid.kind=random, grid.n_points={_shown(cfg.grid.n_points)}"}.get(
            cfg.grid.kind, "grid.kind=stored")
        raise ValueError(
            f"the evaluation would hold about {size_text(cost.rollout_memory_bytes)} ({cost.trajectories} trajectories "
            f"× {cost.frames} frames × {cost.points} points"
            f"{f' × {cost.field_dim} components' if cost.field_dim > 1 else ''}: {span}, {grid}, "
            f"max_trajectories={_shown(cfg.get('max_trajectories'))}, figures={_shown(cfg.figures)}), over the limit "
            f"of {size_text(limit)} ({where}): lower horizon or max_trajectories, raise dt, evaluate on fewer points "
            f"(grid.resolution, grid.n_points or grid.kind=stored) or keep fewer figures; or raise "
            f"max_memory_gb if the machine has the memory")
    if cost.long_memory_bytes > limit:
        raise ValueError(f"long_steps={_shown(cfg.long_steps)} × long_trajectories={cost.long_trajectories} would "
                         f"hold about {size_text(cost.long_memory_bytes)} of recorded states and energies, over the "
                         f"limit of {size_text(limit)} ({where}): lower long_steps or long_trajectories, or raise max_memory_gb "
                         f"if the machine has the memory")


def rollout_request(cfg: DictConfig, model: Any, split: Any, path: Path,
                    provenance: Callable[[], None]) -> tuple[EvaluationData, EvaluationSpec]:
    """The trajectories `cfg` asks to evaluate on the loaded `split` of the dataset at `path`, and how: times, horizon,
    initial states and evaluation grid checked against what the data and the scene can give, the cost logged, then
    `provenance()` called (the run's record is written), then the ground truth simulated where the stored
    trajectories do not cover what was asked."""
    scene = model.scene
    n = len(split) if cfg.max_trajectories is None else min(int(cfg.max_trajectories), len(split))
    dt = float(cfg.dt) if cfg.dt is not None else float(split.times[1] - split.times[0])
    horizon = float(cfg.horizon) if cfg.horizon is not None else float(split.times[-1] + split.times[1] - split.times[0])
    # a whole number ≥ 2 of dt, train_horizon within the horizon (neither set: the data's own frames)
    frames = rollout_frames(cfg, dt, horizon) if cfg.dt is not None or cfg.horizon is not None else len(split.times)
    if cfg.dt is None and cfg.horizon is None and cfg.train_horizon is not None:
        rollout_frames(cfg, dt, dt * frames)  # only train_horizon to check
    cost, *span = planned_cost(cfg, model, dict(model.checkpoint.get("data") or {}), split)
    check_budget(cfg, cost, *span)  # the data's own sizes, before simulating
    train_horizon = float(cfg.train_horizon) if cfg.train_horizon is not None else float(split.times[split.train_times])
    times = dt * np.arange(frames)
    if not times[-1] >= train_horizon - 1e-9 * max(1.0, train_horizon):
        (log.warning if cfg.train_horizon is not None else log.info)(
            "train_horizon=%s (%s) comes after the last frame, t = %g s: the metrics have no extrapolation window",
            _shown(cfg.train_horizon) if cfg.train_horizon is not None else f"{train_horizon:g}",
            "as set" if cfg.train_horizon is not None else "the data's training horizon", times[-1])
    stored_times = len(times) == len(split.times) and np.allclose(times, split.times)
    has_states = split.states.shape[-1] > 0
    if (not stored_times or cfg.get("initial_states") is not None) and \
            not (scene.capabilities()["simulator"] and has_states):
        asked = ", ".join(f"{k}={cfg.get(k)}" for k in ("dt", "horizon", "initial_states") if cfg.get(k) is not None)
        lacking = f"{path} holds no full-order states" if not has_states else f"scene {scene.name!r} has no simulate()"
        raise ValueError(f"{asked}: other times or initial states need a full-order simulator, and {lacking}; "
                         f"evaluation is limited to the stored times ({len(split.times)} samples at dt = "
                         f"{split.times[1] - split.times[0]:g} s): leave dt, horizon and initial_states unset")
    stored_grid = cfg.grid.kind == "stored"
    if not stored_grid and not (scene.provides("fields") and has_states):
        lacking = f"{path} holds no full-order states" if not has_states else f"scene {scene.name!r} has no fields()"
        raise ValueError(f"grid.kind={cfg.grid.kind}: fields on other points need the scene's fields() of full-order "
                         f"states, and {lacking}; use grid.kind=stored (the points the trajectories were stored on)")
    own_states = cfg.get("initial_states") is None
    initial = None
    if not own_states:
        initial = read_initial_states(cfg.initial_states)
        if initial.ndim != 2 or initial.shape[1] != split.states.shape[-1] or not np.isfinite(initial).all():
            got = repr(initial.tolist()) if initial.size <= 16 else f"an array of shape {initial.shape}"  # e.g. a mesh's state
            raise ValueError(f"initial_states must be a list of finite full-order states, each of "
                             f"{split.states.shape[-1]} numbers {tuple(scene.state_names)}, got {got}")
        stored_times, n = False, len(initial)
    points, grid_shape = evaluation_points(cfg.grid, scene.bounds, split.fine_points)
    quadrature = build(OmegaConf.to_container(cfg.quadrature, resolve=True)) if cfg.get("quadrature") else None
    integrator = OmegaConf.to_container(cfg.integrator, resolve=True)
    # what it will cost (the sizes priced above, the quadrature named), before anything is simulated or rolled out
    cost = replace(cost, quadrature_points=quadrature_size(model, quadrature),
                   trained_quadrature_points=quadrature_size(model))
    log.info("evaluating %s", cost.describe())
    if int(cfg.long_steps) > 0:
        log.info("then the long-horizon energy check: %d trajectories × %d steps (%d integration steps with "
                 "integrator.substeps=%d)", cost.long_trajectories, cost.long_steps, cost.long_rollout_steps,
                 cost.substeps)
    provenance()
    spec = EvaluationSpec(integrator=integrator, quadrature=quadrature, split=str(cfg.split),
                          max_reduction_points=None if cfg.max_reduction_points is None else
                          int(cfg.max_reduction_points), decoding=str(cfg.get("decoding", "auto")),
                          long_steps=int(cfg.long_steps), long_trajectories=int(cfg.long_trajectories),
                          figures=int(cfg.figures), keep_fields=int(cfg.figures), progress=True,
                          closure_shooting_iterations=int(cfg.get("closure_shooting_iterations",
                                                                    EvaluationSpec.closure_shooting_iterations)))
    if stored_times and stored_grid:  # the stored trajectories as they are
        data = EvaluationData.of_split(split, scene, n, grid_shape=grid_shape)
        data.train_horizon = train_horizon
        return data, spec
    if stored_times:
        states = split.states[:n]
    else:
        log.info("simulating the ground truth of %d trajectories × %d samples (dt = %g s)", n, len(times), dt)
        states = simulated_ground_truth(scene, initial if initial is not None else split.states[:n, 0], times,
                                        path.parent / GROUND_TRUTH_FOLDER)
    stored_start = own_states and stored_grid  # the stored fields at t0 start the long-horizon check
    return EvaluationData(
        states, times, points, train_horizon, grid_shape,
        controls=split.controls[:n] if own_states and split.controls is not None else None,
        weights=split.weights if stored_grid else None,
        start_fields=(split.fields[:n, 0], split.velocities[:n, 0]) if stored_start else None), spec
