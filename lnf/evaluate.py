"""Evaluation entry point: ``python -m lnf.evaluate ckpt_path=... [integrator=rk4 dt=... horizon=... grid.kind=...]``.

Loads a checkpoint without training, rolls out the test trajectories with any integrator, time step,
horizon, quadrature and evaluation grid, writes metrics.json and Figure 3 into the Hydra output dir.
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any, Optional

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from lnf.allocator import keep_freed_memory
from lnf.config_keys import check_known_keys
from lnf.dataset import (GROUND_TRUTH_FOLDER, SOURCE_ARRAYS, SPLITS, DatasetConfig, ensure_dataset, load_split,
                         simulated_ground_truth, stored_generation, verify_dataset)
from lnf.decoding_table import check_decoding
from lnf.evaluation import evaluate_rollouts, evaluation_cost, long_horizon_energy, quadrature_size
from lnf.model import build, load
from lnf.quadrature import grid_shape_of, midpoint_grid
from lnf.training.callbacks import save_evaluation_figures, stored_reference, write_json_atomic
from lnf.training.console import quiet_console
from lnf.utils import print_summary, run_metadata

log = logging.getLogger("lnf.evaluate")


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
    target = str(spec.get("_target_", ""))  # read before resolving: a learned dynamics' spec names training keys
    if target.endswith(("TabulatedDynamics", "ReducedDynamics")):
        spec = OmegaConf.to_container(spec, resolve=True) if OmegaConf.is_config(spec) else dict(spec)
    if not hasattr(model, "set_tabulation") or getattr(model, "latent_dynamics", None) is not None:
        raise ValueError(f"dynamics={target.rpartition('.')[2] or spec} applies to our model's pulled-back Lagrangian; "
                         f"the checkpoint {ckpt_path} holds a {type(model).__name__} with its own dynamics")
    if target.endswith("TabulatedDynamics"):
        model.set_tabulation(spec)
    elif target.endswith("ReducedDynamics"):
        model.set_tabulation(None)
    else:
        raise ValueError(f"dynamics: lnf.evaluate can switch between lnf.dynamics.ReducedDynamics and "
                         f"lnf.tabulated.TabulatedDynamics, got _target_={target!r} (learned dynamics are trained)")


@torch.no_grad()
def ensure_code_range(model: Any, path: Path, scene: Any, dcfg: DatasetConfig) -> None:
    """A tabulated dynamics needs the training codes' range; a checkpoint written before lnf recorded it gets
    it here from the training split (its training samples, reduced on the coarse grid)."""
    if getattr(model, "tabulation", None) is None or bool(torch.isfinite(model.code_low).all()):
        return
    train = load_split(path, "train", scene=scene, cfg=dcfg)
    p = model.reference_tensor()
    points = torch.as_tensor(train.coarse_points, dtype=p.dtype)
    fields = torch.as_tensor(train.coarse_fields[:, : train.train_times], dtype=p.dtype).flatten(0, 1)
    codes = torch.cat([model.reduce(points, fields[i:i + 256]) for i in range(0, len(fields), 256)])
    model.track_code_range(codes, reset=True)
    log.info("the checkpoint has no range of training codes: took it from %d training snapshots: %s .. %s",
             len(fields), model.code_low.tolist(), model.code_high.tolist())


GRID_KINDS = ("stored", "uniform", "random")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _number(cfg: DictConfig, key: str, expected: str, positive: bool, null: str = "") -> None:
    """`key` must be a finite number (> 0 if `positive`, else ≥ 0), or null when `null` says what null means."""
    value = OmegaConf.select(cfg, key)
    if value is None and null:
        return
    if _is_number(value) and math.isfinite(value) and (value > 0 if positive else value >= 0):
        return
    raise ValueError(f"{key} must be a finite number {'>' if positive else '≥'} 0 [s] ({expected})"
                     f"{' or null (' + null + ')' if null else ''}, got {value!r}")


def _integer(cfg: DictConfig, key: str, minimum: int, expected: str, null: str = "") -> None:
    """`key` must be an integer ≥ `minimum` (an integral float such as 4.0 passes), or null when `null` is given."""
    value = OmegaConf.select(cfg, key)
    if value is None and null:
        return
    if _is_number(value) and math.isfinite(value) and value == int(value) and value >= minimum:
        return
    raise ValueError(f"{key} must be an integer ≥ {minimum} ({expected}){' or null (' + null + ')' if null else ''}, "
                     f"got {value!r}")


def check_settings(cfg: DictConfig) -> None:
    """Refuse keys lnf.evaluate does not use and settings it cannot run, before anything is loaded or rolled out."""
    check_known_keys(cfg, "evaluate", "lnf.evaluate")
    if OmegaConf.is_missing(cfg, "ckpt_path") or cfg.get("ckpt_path") in (None, ""):
        raise ValueError("ckpt_path is required: the checkpoint to evaluate, e.g. "
                         "ckpt_path=outputs/pendulum/runs/<date>/checkpoints/last.ckpt")
    if cfg.get("split") not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {cfg.get('split')!r}")
    _number(cfg, "dt", "the sample spacing of the evaluation", True, "the data's")
    _number(cfg, "horizon", "how long to roll out", True, "the data's horizon")
    _number(cfg, "train_horizon", "where extrapolation starts", False, "the data's training horizon")
    _integer(cfg, "max_trajectories", 1, "how many trajectories of the split to evaluate", "all of them")
    _integer(cfg, "long_steps", 0, "steps of the long-horizon energy check; 0 skips it")
    _integer(cfg, "long_trajectories", 1, "trajectories of the long-horizon energy check")
    _integer(cfg, "figures", 0, "how many trajectories get a Figure 3; 0 draws none")
    _integer(cfg, "max_reduction_points", 1, "evaluation points that ρ̃ uses", "all of them")
    _integer(cfg, "threads", 1, "torch CPU threads", "torch's default")
    check_decoding(cfg.get("decoding", "auto"))
    kind = OmegaConf.select(cfg, "grid.kind", default="stored")
    if kind not in GRID_KINDS:
        raise ValueError(f"grid.kind must be 'stored', 'uniform' or 'random', got {kind!r}")
    _integer(cfg, "grid.resolution", 1, "points per axis of grid.kind=uniform; below 1 the grid has no points")
    _integer(cfg, "grid.n_points", 1, "points of grid.kind=random; below 1 the grid has no points")
    _integer(cfg, "grid.seed", 0, "the seed of grid.kind=random")


def evaluate(cfg: DictConfig) -> dict[str, float]:
    """Evaluate `cfg.ckpt_path`; returns the metrics (also written to metrics.json).

    Unknown keys and bad settings are refused first (:func:`check_settings`); a figure that cannot be drawn is
    a warning, after metrics.json and run.json are written.
    """
    quiet_console()
    check_settings(cfg)
    keep_freed_memory()  # reuse freed decoding buffers (lnf/allocator.py)
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    output_dir = Path(cfg.paths.output_dir)
    model = load(cfg.ckpt_path)
    scene = model.scene
    choose_dynamics(model, cfg.get("dynamics"), cfg.ckpt_path)
    data = dict(model.checkpoint.get("data") or {})
    if not data:
        raise ValueError(f"checkpoint {cfg.ckpt_path} records no data settings; cannot find its test trajectories")
    path = Path(data.pop("path"))
    on_mismatch = data.pop("on_mismatch", "regenerate")
    explicit = bool(data.pop("explicit_path", False))  # a shared file of another run's settings is not overwritten
    if data.get("source") == SOURCE_ARRAYS:  # a user's trajectories: verified, never regenerated
        dcfg = None
        verify_dataset(path, scene)
        now, then = stored_generation(path), data.get("generation") or {}
        changed = sorted(k for k in set(now) | set(then) if now.get(k) != then.get(k))
        if changed:
            log.warning("%s was rewritten since the checkpoint was trained on it (%s); evaluating the file as it is now",
                        path, "; ".join(f"{k}: trained on {then.get(k)!r}, now {now.get(k)!r}" for k in changed))
    else:
        dcfg = DatasetConfig.from_mapping(data)
        ensure_dataset(scene, dcfg, path, on_mismatch=on_mismatch, overwrite_other_settings=not explicit)
    split = load_split(path, cfg.split, scene=scene, cfg=dcfg)
    ensure_code_range(model, path, scene, dcfg)

    n = len(split) if cfg.max_trajectories is None else min(int(cfg.max_trajectories), len(split))
    dt = float(cfg.dt) if cfg.dt is not None else float(split.times[1] - split.times[0])
    horizon = float(cfg.horizon) if cfg.horizon is not None else float(split.times[-1] + split.times[1] - split.times[0])
    if dt <= 0 or horizon <= dt:
        raise ValueError(f"need dt > 0 and horizon > dt, got dt={dt}, horizon={horizon}")
    train_horizon = float(cfg.train_horizon) if cfg.train_horizon is not None else float(split.times[split.train_times])
    times = dt * np.arange(int(round(horizon / dt)))
    stored_times = len(times) == len(split.times) and np.allclose(times, split.times)
    has_states = split.states.shape[-1] > 0
    if (not stored_times or cfg.get("initial_states") is not None) and \
            not (scene.capabilities()["simulator"] and has_states):
        asked = ", ".join(f"{k}={cfg.get(k)}" for k in ("dt", "horizon", "initial_states") if cfg.get(k) is not None)
        lacking = f"{path} holds no full-order states" if not has_states else f"scene {scene.name!r} has no simulate()"
        raise ValueError(f"{asked}: other times or initial states need a full-order simulator, and {lacking}; "
                         f"evaluation is limited to the stored times ({len(split.times)} samples at dt = "
                         f"{split.times[1] - split.times[0]:g} s): leave dt, horizon and initial_states unset")
    if cfg.grid.kind != "stored" and not (scene.provides("fields") and has_states):
        lacking = f"{path} holds no full-order states" if not has_states else f"scene {scene.name!r} has no fields()"
        raise ValueError(f"grid.kind={cfg.grid.kind}: fields on other points need the scene's fields() of full-order "
                         f"states, and {lacking}; use grid.kind=stored (the points the trajectories were stored on)")
    initial = None
    if cfg.get("initial_states") is not None:
        initial = read_initial_states(cfg.initial_states)
        if initial.ndim != 2 or initial.shape[1] != split.states.shape[-1] or not np.isfinite(initial).all():
            got = repr(initial.tolist()) if initial.size <= 16 else f"an array of shape {initial.shape}"  # e.g. a mesh's state
            raise ValueError(f"initial_states must be a list of finite full-order states, each of "
                             f"{split.states.shape[-1]} numbers {tuple(scene.state_names)}, got {got}")
        stored_times, n = False, len(initial)
    points, grid_shape = evaluation_points(cfg.grid, scene.bounds, split.fine_points)
    use_stored = stored_times and cfg.grid.kind == "stored"
    quadrature = build(OmegaConf.to_container(cfg.quadrature, resolve=True)) if cfg.get("quadrature") else None
    integrator = OmegaConf.to_container(cfg.integrator, resolve=True)
    # what it will cost, before anything is simulated or rolled out
    cost = evaluation_cost(n, len(times), len(points), scene.field_dim, keep_fields=int(cfg.figures),
                           quadrature_points=quadrature_size(model, quadrature),
                           trained_quadrature_points=quadrature_size(model))
    log.info("evaluating %s", cost.describe())
    if int(cfg.long_steps) > 0:
        log.info("then the long-horizon energy check: %d trajectories × %d steps", min(int(cfg.long_trajectories), n),
                 int(cfg.long_steps))
    if stored_times:
        states = split.states[:n]
    else:
        log.info("simulating the ground truth of %d trajectories × %d samples (dt = %g s)", n, len(times), dt)
        states = simulated_ground_truth(scene, initial if initial is not None else split.states[:n, 0], times,
                                        path.parent / GROUND_TRUTH_FOLDER)

    start = time.perf_counter()
    own_states = cfg.get("initial_states") is None
    reference = stored_reference(split, scene, n) if use_stored else {}
    if own_states and split.controls is not None:
        reference["controls"] = split.controls[:n]
    if cfg.grid.kind == "stored" and split.weights is not None:
        reference["weights"] = split.weights
    result = evaluate_rollouts(model, states, times, points, train_horizon,
                               true_fields=split.fields[:n] if use_stored else None,
                               true_velocities=split.velocities[:n] if use_stored else None,
                               integrator=integrator, quadrature=quadrature, grid_shape=grid_shape,
                               max_reduction_points=cfg.max_reduction_points, label=f"{cfg.split} rollout",
                               keep_fields=int(cfg.figures), progress=True, decoding=str(cfg.get("decoding", "auto")), **reference)
    metrics = dict(result.metrics)
    if int(cfg.long_steps) > 0:
        k = min(int(cfg.long_trajectories), len(states))
        stored_start = own_states and cfg.grid.kind == "stored"  # the stored fields at t0 start the check
        metrics.update(long_horizon_energy(
            model, states[:k, 0], points, dt, int(cfg.long_steps), integrator=integrator, quadrature=quadrature,
            grid_shape=grid_shape, max_reduction_points=cfg.max_reduction_points,
            initial_fields=(split.fields[:k, 0], split.velocities[:k, 0]) if stored_start else None,
            controls=split.controls[:k] if own_states and split.controls is not None else None, progress=True))
    metrics["evaluation_seconds"] = time.perf_counter() - start
    write_json_atomic(output_dir / "metrics.json", metrics)
    write_json_atomic(output_dir / "run.json", run_metadata(cfg))
    if int(cfg.figures) > 0:
        try:  # the results are written: a figure that fails (a plotting backend, a full disk) must not cost them
            save_evaluation_figures(result, scene, grid_shape, train_horizon, output_dir / "figures", cfg.split,
                                    int(cfg.figures), integrator=integrator)
        except Exception as err:  # noqa: BLE001
            log.warning("could not draw Figure 3: %s: %s (metrics.json and run.json are written in %s)",
                        type(err).__name__, err, output_dir)
    print_summary(metrics, title=f"{cfg.split} metrics of {cfg.ckpt_path}")
    return metrics


@hydra.main(version_base="1.3", config_path="pkg://lnf.conf", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    evaluate(cfg)


if __name__ == "__main__":
    main()
