"""Acceptance measurements of a trained scene, chosen by what the scene declares.

    python -m lnf.train +experiment=<scene>            # train first (a run under outputs/<scene>/runs/)
    python -m experiments.scenes --scene <scene>      # every measurement the scene's declarations allow, on its newest run
    python -m experiments.scenes --scene <scene> --measure modes --max-modes 12     # only some of them
    python -m experiments.scenes --scene elastic --dynamics tabulated   # our rollouts with the tabulated M̃, Ṽ
    python -m experiments.scenes --scene elastic_actuated --unseen-load 0.5 1.2     # the load of docs/benchmarks/scenes.md
    PYTHONPATH=examples python -m experiments.scenes --config-dir examples/conf --scene vibrating_string \\
        --ckpt <run>/checkpoints/last.ckpt                                           # a scene of your own

The measurements, and what each asks of the scene (``lnf.scenes.Scene``):

- ``black_box``: valid prediction time and the 20×-horizon energy drift of ours against the black-box latent
  MLP, fitted here to the same embedding's training codes (``vpt.png``). Where ``Scene.baselines()["latent_mlp"]``.
- ``modes``: the test error against the number of linear modes, POD-Galerkin rollouts with k = 1 … --max-modes
  modes and the best linear k-mode projection (an SVD of the training fields), and the k that match our error
  (``modes.png``). Where ``Scene.baselines()["pod"]``.
- ``speedup``: where ``Scene.expensive_reference`` (the full-order reference is itself a costly discretisation):
  the largest step of the reference (if its ``simulate`` takes a ``time_step``: 1 … 1.8 × the scene's own
  ``time_step``) and of our rollout that meet --target in the training horizon, and the speed-up of our rollout
  over the reference, timed back to back, without and with decoding every stored frame on the evaluation points
  (``energy.png``, ``tip.png``).
- ``loads``: where ``Scene.has_controls``: the test loads and one load not seen in training (--unseen-load, or
  each load parameter beyond the training trajectories' range by half its width) (``tip_unseen_load.png``).
- ``shape``: where the body and its displacement are 3-D: the deformed body at four times, ours against the
  reference (``shape.png``).
- ``decay``: where the scene is not conservative (``Scene.is_conservative`` false) and has reference energies:
  the free decay of the test initial states, without their loads (``decay.png``).
- ``damped``: where the scene is conservative and can add a damping (``Scene.with_damping``): the test initial
  states under mass-proportional damping α = --damping, the reference re-simulated with it and our model, trained
  without it, given the pulled-back damping force −α M̃ q̃̇ and no retraining (exact pullback: the table holds the
  conservative parts only) (``damped.png``, ``damped_tip.png``).

To set a trajectory's load the study uses the scene's ``with_controls(states, controls)`` if it has one, else the
last c entries of the full-order state where ``Scene.controls`` reads them from there. ``tip*.png`` draw the field
at the point (and component) that moves most in the test set. Each run writes ``<out>/{results.json, *.png}``
(default out: ``outputs/scenes/<scene>``); ``results.json`` lists the measurements it ran and why the others
were skipped. Every number is measured here, in one process, on the machine it runs on (threads: all cores
unless --threads).
"""
from __future__ import annotations

import argparse
import math
import json
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import torch

from experiments import studylib
from experiments.scene_measurements import (Context, Skipped, black_box, damped, decay, experiment_integrator_order,
                                            loads, modes, shape, snapshot_data_of, speedup, timed, unseen_load,
                                            with_controls)
from lnf.evaluation_pipeline import ensure_code_range
from lnf.model import load
from lnf.tempfiles import write_json_atomic

__all__ = ["applicable", "main", "merge", "snapshot_data_of", "timed", "unseen_load", "with_controls"]

ROOT = Path(__file__).resolve().parents[1]


def _why_not_shape(scene: Any) -> Optional[str]:
    return None if scene.body_dim == 3 and scene.field_dim == 3 else \
        "its body is not 3-D with a 3-D displacement field (the deformed-shape view is a 3-D one)"


# ---------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Measurement:
    """One measurement: what it does, and why a scene cannot have it (None: it can)."""

    run: Callable[[Context], dict[str, Any]]
    why_not: Callable[[Any], Optional[str]]


def _no_simulator(scene: Any) -> Optional[str]:
    return None if scene.capabilities()["simulator"] else "it re-simulates the reference, and the scene has no simulator"


def _why_not_black_box(scene: Any) -> Optional[str]:
    return None if scene.baselines().get("latent_mlp", True) else \
        "its baselines() says the black-box latent MLP cannot run it (latent_mlp: False)"


def _why_not_modes(scene: Any) -> Optional[str]:
    return None if scene.baselines().get("pod", True) else "its baselines() says POD-Galerkin cannot run it (pod: False)"


def _why_not_speedup(scene: Any) -> Optional[str]:
    if not scene.expensive_reference:
        return "its full-order reference is not expensive (Scene.expensive_reference is False)"
    return _no_simulator(scene)


def _why_not_loads(scene: Any) -> Optional[str]:
    return "it has no loads (Scene.has_controls is False)" if not scene.has_controls else _no_simulator(scene)


def _why_not_decay(scene: Any) -> Optional[str]:
    if scene.is_conservative:
        return "it is conservative (Scene.is_conservative): nothing decays"
    if not scene.capabilities()["true_energies"]:
        return "it has no reference energies (true_energy_parts)"
    return _no_simulator(scene)


def _why_not_damped(scene: Any) -> Optional[str]:
    if not scene.is_conservative:
        return "it is not conservative: its own damping or loads act (see decay)"
    if not scene.capabilities()["damping"]:
        return "it cannot add a damping (Scene.with_damping)"
    if not scene.capabilities()["true_energies"]:
        return "it has no reference energies (true_energy_parts)"
    return _no_simulator(scene)


MEASUREMENTS: dict[str, Measurement] = {
    "black_box": Measurement(black_box, _why_not_black_box),
    "modes": Measurement(modes, _why_not_modes),
    "speedup": Measurement(speedup, _why_not_speedup),
    "loads": Measurement(loads, _why_not_loads),
    "decay": Measurement(decay, _why_not_decay),
    "damped": Measurement(damped, _why_not_damped),
    "shape": Measurement(shape, _why_not_shape),
}


def applicable(scene: Any) -> dict[str, Optional[str]]:
    """Each measurement → None where the scene's declarations allow it, else why not."""
    return {name: m.why_not(scene) for name, m in MEASUREMENTS.items()}


def merge(result: dict[str, Any], part: dict[str, Any], name: str) -> None:
    """A measurement's keys into the results: the "ours" metrics of several merge (they come from one rollout);
    any other key is one measurement's own."""
    for key, value in part.items():
        if key == "ours":
            result.setdefault("ours", {}).update(value)
        elif key in result:
            raise RuntimeError(f"measurement {name!r} writes {key!r}, which another one wrote already")
        else:
            result[key] = value


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m experiments.scenes", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config-dir", type=Path, default=None, metavar="DIR",
                        help="a Hydra config folder of your own, as `python -m lnf.train --config-dir DIR` takes it "
                             "(the scene's module must be importable: PYTHONPATH)")
    parser.add_argument("--scene", default=None,
                        help="the experiment (conf/experiment/<scene>.yaml or DIR/experiment/<scene>.yaml): names the "
                             "default checkpoint and output folder; optional with --ckpt")
    parser.add_argument("--ckpt", default=None, help="default: the newest outputs/<scene>/runs/*/checkpoints/last.ckpt (the folder "
                             "`python -m lnf.train +experiment=<scene>` trains into)")
    parser.add_argument("--out", default=None, help="default: outputs/scenes/<scene>")
    parser.add_argument("--measure", nargs="+", choices=sorted(MEASUREMENTS), default=None,
                        help="measurements to run (default: every one the scene's declarations allow)")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--integrator-order", type=int, choices=[2, 4], default=None,
                        help="order of the implicit midpoint rule of our rollouts (default: the experiment's "
                             "integrator.order, as lnf.train rolls out)")
    parser.add_argument("--dynamics", choices=["checkpoint", "lagrangian", "tabulated"], default="checkpoint",
                        help="our rollouts: as the checkpoint was trained, the exact pullback, or the tabulated one "
                             "(speedup also times the exact one for comparison)")
    parser.add_argument("--max-modes", type=int, default=12, help="modes: POD modes k = 1 … this")
    parser.add_argument("--bb-iterations", type=int, default=2000,
                        help="black_box: training iterations of the black box's latent MLP")
    parser.add_argument("--target", type=float, default=0.05,
                        help="speedup: the in-horizon field error that the reference's and our steps must meet")
    parser.add_argument("--unseen-load", type=float, nargs="+", default=None, metavar="C",
                        help="loads: the load parameters not seen in training (default: beyond the training range)")
    parser.add_argument("--damping", type=float, default=0.5, metavar="ALPHA",
                        help="damped: the mass-proportional damping rate α [1/s] (default 0.5)")
    args = parser.parse_args(argv)
    if not (math.isfinite(args.damping) and args.damping > 0):
        parser.error(f"--damping must be a rate > 0 [1/s], got {args.damping}")
    if args.scene is None and args.ckpt is None:
        parser.error("give --scene (its newest run's checkpoint is used) or --ckpt")
    config_dir = args.config_dir.expanduser().resolve() if args.config_dir else None
    if config_dir is not None and not config_dir.is_dir():
        parser.error(f"--config-dir {args.config_dir}: no such folder ({config_dir})")
    if args.scene is not None:
        try:
            studylib.experiment_file(args.scene, config_dir)
        except FileNotFoundError as err:
            parser.error(f"--scene {args.scene!r}: {err}" + ("" if config_dir else " (a scene of your own: give its "
                                                              "config folder with --config-dir)"))
    if args.threads:
        torch.set_num_threads(args.threads)
    train = f"python -m lnf.train{f' --config-dir {config_dir}' if config_dir else ''} +experiment={args.scene}"
    if args.ckpt:
        ckpt = Path(args.ckpt).resolve()
        if not ckpt.exists():
            raise SystemExit(f"--ckpt {args.ckpt}: no such file ({ckpt})")
    else:
        runs = ROOT / "outputs" / str(args.scene) / "runs"
        found = sorted(runs.glob("*/checkpoints/last.ckpt"), key=lambda p: p.stat().st_mtime)
        if not found:
            raise SystemExit(f"no checkpoint under {runs}/*/checkpoints/last.ckpt; train first: {train} "
                             f"(or give --ckpt)")
        ckpt = found[-1]
        print(f"checkpoint: {ckpt} (the newest under {runs})")
    # the scene of --config-dir/--scene was named by the user: its checkpoint may name that scene's module
    trust = studylib.Study(name="scenes", scene=args.scene, mode="reduced", out=ROOT, threads=1,
                           config_dir=config_dir).trusted_modules() if args.scene is not None else []
    model = load(ckpt, trust=trust)
    model.eval()
    name = args.scene or model.scene.name
    out = Path(args.out).resolve() if args.out else ROOT / "outputs" / "scenes" / name
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    reasons = applicable(model.scene)
    chosen = args.measure or [m for m, why in reasons.items() if why is None]
    refused = [f"{m}: {reasons[m]}" for m in chosen if reasons[m] is not None]
    if refused:
        raise SystemExit(f"--measure: scene {name!r} cannot have {'; '.join(refused)}")
    for m, why in reasons.items():
        if m not in chosen:
            print(f"[scenes] {m}: " + (f"skipped, {why}" if why else "not asked for (--measure)"), flush=True)
    dm = snapshot_data_of(model)
    if args.dynamics != "checkpoint" and hasattr(model, "set_tabulation"):
        model.set_tabulation((model.tabulation or {}) if args.dynamics == "tabulated" else None)
    if getattr(model, "tabulation", None) is not None:
        ensure_code_range(model, Path(dm.path), dm.config)
    order = args.integrator_order or experiment_integrator_order(name, config_dir)
    ctx = Context(model=model, dm=dm, out=out, options=args, integrator={"name": "implicit_midpoint", "order": order})
    print(f"[scenes] our rollouts: the implicit midpoint rule of order {order}", flush=True)
    result: dict[str, Any] = {"scene": name, "measurements": [], "skipped": {}}
    for m in chosen:
        print(f"[scenes] {m} ...", flush=True)
        try:
            part = MEASUREMENTS[m].run(ctx)
        except Skipped as why:
            if args.measure:
                raise SystemExit(f"--measure {m}: {why}")
            print(f"[scenes] {m}: skipped, {why}", flush=True)
            result["skipped"][m] = str(why)
            continue
        merge(result, part, m)
        result["measurements"].append(m)
    result["skipped"].update({m: why for m, why in reasons.items() if why is not None})
    result["dynamics"] = "tabulated" if getattr(model, "tabulation", None) is not None else "lagrangian"
    result["integrator"] = ctx.integrator
    result["seconds"] = time.perf_counter() - start
    result["checkpoint"] = str(ckpt)
    result["machine"] = {"platform": platform.platform(), "processor": platform.processor(),
                         "torch": torch.__version__, "threads": torch.get_num_threads()}
    write_json_atomic(out / "results.json", result)
    print(json.dumps(result, indent=1, default=str))
    return result


if __name__ == "__main__":
    main()
