"""A study's settings and command line (:class:`Study`, :func:`parse_args`) and the configs it reads."""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Optional, Sequence

from omegaconf import OmegaConf

from experiments.studylib.jobs import CONF, ROOT, absolute_pythonpath, job_environment, run_in_worker
from experiments.studylib.results import all_done, collect, keep_aside, write_csv
from experiments.studylib.tables import write_text_atomic

# The methods compared in every chart: label → overrides that select them (docs/method.md §7.5)
METHODS: dict[str, list[str]] = {
    "lnf": [],
    "latent_mlp": ["dynamics=latent_mlp"],
    # the exact pullback: a scene experiment may choose dynamics=tabulated, which needs a neural field's codes
    "pod": ["model=pod", "dynamics=lagrangian"],
    "full_order": ["model=full_order", "dynamics=lagrangian"],
}
# Operator Inference (experiments/operator_inference.py study_rows: fitted in the study's process, not a Hydra job)
# "opinf" reads the full fine-grid training states; "opinf_observed" only lnf's sparse observations (gappy POD)
CHARTED = (*METHODS, "lnf_closure", "opinf", "opinf_observed")
COMMON = ["logger=csv", "evaluation.every_n_epochs=0", "evaluation.figures=0", "trainer.enable_progress_bar=false"]
# Reduced settings (each study under 30 min on 2 CPU cores): smaller SIREN, 15 epochs, higher lr
REDUCED_NEURAL = ["model.width=64", "model.hyper_width=64", "trainer.max_epochs=15", "optimizer.lr=2e-3"]
SMOKE_DATA = ["data.n_train=3", "data.n_val=1", "data.n_test=2", "data.n_times=20", "data.train_times=10",
              "data.fine_resolution=12", "data.coarse_resolution=16", "data.batch_size=8"]
#: an untrained one-epoch model is often stiff: its rollouts take at most 4 automatic substeps instead of 64; its
#: training fits no closure (a scene's experiment may ask for one): the Pareto study's closure sweep fits one
SMOKE_NEURAL = ["model.width=16", "model.hyper_width=8", "trainer.max_epochs=1", "quadrature.order=4",
                "evaluation.max_reduction_points=64", "integrator.max_substeps=4", "model.closure_degree=0"]


@dataclass
class Study:
    """Settings of one study run, from the command line."""

    name: str
    scene: str
    mode: str  # "reduced" | "full" | "smoke"
    out: Path
    threads: int
    fresh: bool = False
    #: the user's Hydra config folder (absolute), searched after conf/ as ``--config-dir`` makes Hydra do; or None
    config_dir: Optional[Path] = None
    #: run the multiruns one after another in one worker process (see :class:`JobWorker`); False: a fresh
    #: `python -m <entry>` process each (--fresh-processes)
    one_process: bool = True
    long_check: bool = True  # the training jobs' long-horizon energy check (off where a study reads none of it)
    #: Hydra overrides of the user's (``--set KEY=VALUE``), after the study's own settings of every training job
    overrides: tuple[str, ...] = ()
    rows: list[dict[str, Any]] = field(default_factory=list)
    started: float = field(default_factory=time.perf_counter)
    _scene: Any = field(default=None, init=False, repr=False, compare=False)

    # -- settings -------------------------------------------------------------------------------
    def base(self) -> list[str]:
        """Overrides shared by every training job of the study."""
        out = [f"+experiment={self.scene}", *COMMON, f"threads={self.threads}"]
        if self.mode == "smoke":
            out += SMOKE_DATA
        if not self.long_check:
            out.append("evaluation.long_steps=0")
        elif self.mode == "smoke":
            out += ["evaluation.long_steps=10", "evaluation.long_trajectories=1"]
        return out

    def neural(self) -> list[str]:
        """Extra overrides of the neural methods (ours and the black box) for this mode."""
        if self.mode == "smoke":
            return SMOKE_NEURAL
        return REDUCED_NEURAL if self.mode == "reduced" else []

    def method(self, name: str, extra: Sequence[str] = ()) -> list[str]:
        """Overrides selecting method `name` with this mode's settings, plus `extra`."""
        over = [*self.base(), *METHODS[name]]
        if name == "latent_mlp":  # its RK4 takes none of the midpoint settings a scene experiment may set
            over += [f"~integrator.{key}" for key in self.unused_experiment_keys("integrator", "integrator/rk4")]
        if name in ("lnf", "latent_mlp"):
            over += self.neural()
            if name == "latent_mlp" and self.mode == "smoke":
                over += ["dynamics.iterations=10"]
        else:
            over += [f"~model.{key}" for key in self.unused_experiment_keys("model", f"model/{name}")]
            if self.mode == "smoke":
                over += ["evaluation.max_reduction_points=64"]
                if name == "full_order":
                    over += ["model.resolution=12"]
        return [*over, *self.overrides, *extra]  # the user's last but for the study's own sweep

    def unused_experiment_keys(self, node: str, config: str) -> list[str]:
        """Keys of the scene experiment's `node` (e.g. a SIREN width under `model`) that `config` (e.g.
        model/pod) does not have: they are deleted, since `+experiment=<scene>` merges them into any choice."""
        own = OmegaConf.load(config_file(config, self.config_dir))
        experiment = OmegaConf.load(experiment_file(self.scene, self.config_dir))  # as written, not composed
        return sorted(set(experiment.get(node) or {}) - set(own))

    def hydra_args(self) -> list[str]:
        """``--config-dir DIR`` for `python -m lnf.train` and `python -m lnf.evaluate` (none without a config dir)."""
        return [] if self.config_dir is None else ["--config-dir", str(self.config_dir)]

    def composed(self, extra: Sequence[str] = ()) -> Any:
        """The training config as `python -m lnf.train [--config-dir DIR] +experiment=<scene> <extra>` composes it,
        with its `hydra` node (`hydra.runtime.choices` names the option chosen in each config group)."""
        from hydra import compose, initialize_config_dir

        overrides = [f"+experiment={self.scene}", *extra]
        if self.config_dir is not None:  # what --config-dir does: the folder is searched after conf/
            overrides.append(f"hydra.searchpath=['file://{self.config_dir}']")
        with initialize_config_dir(str(CONF), version_base=None):
            return compose("train", overrides=overrides, return_hydra_config=True)

    def scene_object(self) -> Any:
        """The scene of the study's experiment (a :class:`lnf.scenes.Scene`), built once from the composed
        config: what the study asks what the scene can do."""
        if self._scene is None:
            from lnf.model import build

            self._scene = build(OmegaConf.to_container(self.composed().scene, resolve=True))
        return self._scene

    def trusted_modules(self) -> list[str]:
        """The module of the study's scene when it is not one of lnf's: the study was asked to run that scene
        (--config-dir, --scene), so the checkpoints it trains may name it (see lnf.trust)."""
        target = str(self.composed().scene.get("_target_") or "")
        top = target.split(".")[0]
        return [top] if top and top != "lnf" else []

    def is_default_scene(self) -> bool:
        """Whether the study runs the default experiment (no --scene given, see :func:`default_experiment`)."""
        return self.scene == default_experiment()

    def command(self) -> str:
        """The command line that reruns this study (its mode, config dir and scene) from the repository root, as
        summaries and captions print it; with a config dir, the PYTHONPATH that imports the scene's module (less the
        repository root itself, which `python -m` run there puts on the path)."""
        mode = ("" if self.mode == "reduced" else f" --{self.mode}") + "".join(f" --set {o}" for o in self.overrides)
        if self.config_dir is None:
            scene = "" if self.is_default_scene() else f" --scene {self.scene}"
            return f"python -m experiments.{self.name}{mode}{scene}"
        path = [_shown(Path(p)) for p in absolute_pythonpath(os.environ.get("PYTHONPATH", "")).split(os.pathsep)
                if p and Path(p) != ROOT]
        env = f"PYTHONPATH={os.pathsep.join(path)} " if path else ""
        return (f"{env}python -m experiments.{self.name}{mode} --config-dir {_shown(self.config_dir)} "
                f"--scene {self.scene}")

    def supports(self, name: str) -> bool:
        """Whether method `name` can run this study's scene, as the scene declares (``Scene.baselines()``; a
        method it does not list can)."""
        return bool(self.scene_object().baselines().get(name, True))

    # -- running --------------------------------------------------------------------------------
    def multirun(self, sweep: str, overrides: Sequence[str], entry: str = "lnf.train",
                 label: Optional[dict[str, Any]] = None) -> list[dict[str, Any]]:
        """Run (or reuse) one Hydra multirun into out/<sweep>; returns its rows (also kept in self.rows)."""
        folder = self.out / sweep
        if entry == "lnf.evaluate" and self.trusted_modules():
            overrides = [*overrides, f"trust=[{','.join(self.trusted_modules())}]"]
        cmd = [sys.executable, "-m", entry, *self.hydra_args(), "-m", *overrides, f"hydra.sweep.dir={folder}",
               "hydra.sweep.subdir=${hydra.job.num}"]
        stamp = folder / "command.json"
        if stamp.is_file() and json.loads(stamp.read_text()) == cmd[1:] and all_done(folder) and not self.fresh:
            print(f"[{self.name}] reusing {folder}")
        else:
            if folder.exists():
                kept = keep_aside(folder)
                print(f"[{self.name}] {sweep}: the results already there (another command, unfinished, or --fresh) "
                      f"are kept as {kept}", flush=True)
            folder.mkdir(parents=True)
            print(f"[{self.name}] {sweep}: python -m {entry} {' '.join(self.hydra_args() + ['-m'])} "
                  f"{' '.join(overrides)}", flush=True)
            t0 = time.perf_counter()
            log = folder / "multirun.log"
            if self.one_process:
                returncode = run_in_worker(entry, cmd[3:], log)
            else:
                with open(log, "w") as fh:
                    returncode = subprocess.run(cmd, cwd=ROOT, env=job_environment(), stdout=fh,
                                                stderr=subprocess.STDOUT).returncode
            if returncode != 0:
                tail = log.read_text()[-3000:]
                raise RuntimeError(f"sweep {sweep} failed (exit {returncode}); log {log}:\n{tail}")
            write_text_atomic(stamp, json.dumps(cmd[1:], indent=1))
            print(f"[{self.name}] {sweep}: done in {time.perf_counter() - t0:.0f} s", flush=True)
        rows = collect(folder, sweep, label)
        self.rows += rows
        return rows

    def write_csv(self, name: str, rows: Optional[list[dict[str, Any]]] = None) -> Path:
        return write_csv(self.out / name, self.rows if rows is None else rows)

    def machine(self) -> str:
        import torch

        return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores visible, "
                f"torch {torch.__version__}, {self.threads} threads")

    def finish(self, outputs: Iterable[Path]) -> None:
        print(f"[{self.name}] {self.mode} study finished in {(time.perf_counter() - self.started) / 60:.1f} min "
              f"on {self.machine()}")
        for p in outputs:
            print(f"  wrote {p}")


def default_experiment() -> str:
    """The experiment a study runs without ``--scene``: the one named like the default ``scene`` of the training
    config (conf/train.yaml), i.e. what ``python -m lnf.train`` trains without overrides."""
    for entry in OmegaConf.load(ROOT / "conf" / "train.yaml").get("defaults", []):
        if not isinstance(entry, str) and entry.get("scene"):  # `- scene: <name>`; plain strings are `_self_` etc.
            return str(entry["scene"])
    raise RuntimeError("conf/train.yaml names no default scene (defaults: - scene: <name>)")


def config_file(config: str, config_dir: Optional[Path] = None) -> Path:
    """The file of config `config` (e.g. ``model/pod`` or ``experiment/<scene>``) that Hydra composes: conf/'s,
    else the config dir's (``--config-dir`` searches its folder after conf/)."""
    for folder in (CONF, config_dir):
        if folder is not None and (folder / f"{config}.yaml").is_file():
            return folder / f"{config}.yaml"
    where = " or ".join(str(f / f"{config}.yaml") for f in (CONF, config_dir) if f is not None)
    raise FileNotFoundError(f"no config {config}: looked for {where}")


def experiment_file(scene: str, config_dir: Optional[Path] = None) -> Path:
    """``experiment/<scene>.yaml`` of conf/ or of the config dir (see :func:`config_file`)."""
    return config_file(f"experiment/{scene}", config_dir)


def _shown(path: Path) -> str:
    """`path` as a command run from the repository root names it: relative inside the repository, else absolute."""
    path = Path(path).resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def parse_args(name: str, description: str, argv: Optional[Sequence[str]] = None,
               extra: Optional[Callable[[argparse.ArgumentParser], Any]] = None) -> tuple[Study, argparse.Namespace]:
    """The study's command line: ``--config-dir``, ``--scene``, ``--full``/``--smoke``, ``--out``, ``--threads``,
    ``--fresh``, ``--set`` and the study's own options (`extra` adds them to the parser)."""
    p = argparse.ArgumentParser(prog=f"python -m experiments.{name}", description=description,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    default = default_experiment()
    p.add_argument("--config-dir", type=Path, default=None, metavar="DIR",
                   help="a Hydra config folder of your own (DIR/scene/<name>.yaml, DIR/experiment/<name>.yaml), "
                        "searched after conf/ as `python -m lnf.train --config-dir DIR` does; the scene's module "
                        "must be importable (PYTHONPATH)")
    p.add_argument("--scene", default=default,
                   help=f"experiment config of the scene (conf/experiment/<scene>.yaml or DIR/experiment/<scene>.yaml; "
                        f"default {default})")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--full", action="store_true", help="the full study (default model size and training budget)")
    g.add_argument("--smoke", action="store_true", help="tiny settings (the test suite's smoke test)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default outputs/studies/<study>[-<mode>])")
    p.add_argument("--threads", type=int, default=2, help="torch threads per job")
    p.add_argument("--fresh", action="store_true", help="rerun sweeps even if their results exist")
    p.add_argument("--fresh-processes", action="store_true",
                   help="run each multirun in a fresh `python -m lnf.train` (or lnf.evaluate) process; default: one "
                        "after another in one worker process, which imports torch and Lightning once")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                   help="a Hydra override of every training job, after the study's own settings (repeatable), e.g. "
                        "--set evaluation.closure_shooting_iterations=0; summaries print it in their command")
    if extra is not None:
        extra(p)
    args = p.parse_args(argv)
    for given in args.overrides:
        if "=" not in given or given.startswith("="):
            p.error(f"--set {given!r}: expected a Hydra override KEY=VALUE, e.g. --set trainer.max_epochs=30")
    config_dir = None
    if args.config_dir is not None:
        config_dir = args.config_dir.expanduser().resolve()
        if not config_dir.is_dir():
            p.error(f"--config-dir {args.config_dir}: no such folder ({config_dir})")
    try:
        experiment_file(args.scene, config_dir)
    except FileNotFoundError:
        if config_dir is None:
            p.error(f"--scene {args.scene!r}: no {CONF / 'experiment' / f'{args.scene}.yaml'} (a scene of your own: "
                    f"give its config folder with --config-dir DIR, which holds DIR/experiment/{args.scene}.yaml)")
        p.error(f"--scene {args.scene!r}: neither {CONF / 'experiment' / f'{args.scene}.yaml'} nor "
                f"{config_dir / 'experiment' / f'{args.scene}.yaml'} exists")
    mode = "full" if args.full else "smoke" if args.smoke else "reduced"
    out = args.out.expanduser().resolve() if args.out else \
        ROOT / "outputs" / "studies" / (name if mode == "reduced" else f"{name}-{mode}")
    if args.scene != default and args.out is None:
        out = out.with_name(f"{out.name}-{args.scene}")
    study = Study(name=name, scene=args.scene, mode=mode, out=out, threads=args.threads, fresh=args.fresh,
                  config_dir=config_dir, one_process=not args.fresh_processes, overrides=tuple(args.overrides))
    try:
        scene = study.scene_object()
    except (ImportError, ValueError) as err:  # a module not on PYTHONPATH, a bad scene parameter
        p.error(f"--scene {args.scene}: its scene cannot be built: {err}")
    if not scene.capabilities()["simulator"]:
        p.error(f"--scene {args.scene}: scene {type(scene).__qualname__} has no simulator (simulate() and "
                f"sample_initial_states()); the studies generate each mode's dataset with it and re-simulate the "
                f"reference at other times, grids and initial states")
    return study, args

