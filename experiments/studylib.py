"""Shared machinery of the benchmark studies in experiments/: Hydra multiruns, CSV tables, charts.

Each study script runs `python -m lnf.train -m ...` (and `python -m lnf.evaluate -m ...`) as Hydra
multiruns into ``outputs/studies/<study>/<sweep>/<job>/``, collects every job's ``metrics.json`` with
its overrides into one CSV, and draws its charts from that CSV. A sweep whose jobs all finished with the
same command is reused (pass --fresh to rerun it); a folder that is not reused is renamed
``<sweep>.replaced-<UTC time>``, never deleted (:func:`keep_aside`). Every study takes
``--scene`` (any ``conf/experiment/<scene>.yaml``, or ``<DIR>/experiment/<scene>.yaml`` of a config folder of
your own given with ``--config-dir DIR``, as ``python -m lnf.train --config-dir DIR`` takes it), ``--full`` (the
full study: the default model size and training budget) and ``--smoke`` (tiny settings, for the test suite).

No study names a scene: what a study does on a scene it asks the scene object, built from the composed
experiment config (:meth:`Study.scene_object`): which baselines can run it (``Scene.baselines()``), whether
its full-order reference is expensive (``Scene.expensive_reference``), its stability release cases
(``Scene.stability_cases()``). Without ``--scene`` a study runs the experiment named like the training
config's default scene (:func:`default_experiment`).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Optional, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"

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
CHARTED = (*METHODS, "opinf", "opinf_observed")
LABELS = {"lnf": "LNF (ours)", "latent_mlp": "black-box latent MLP", "pod": "POD-Galerkin", "full_order": "full order",
          "opinf": "Operator Inference (full states)", "opinf_observed": "Operator Inference (sparse observations)"}
COLORS = {"lnf": "tab:blue", "latent_mlp": "tab:red", "pod": "tab:green", "full_order": "tab:gray",
          "opinf": "tab:purple", "opinf_observed": "tab:pink"}
MARKERS = {"lnf": "o", "latent_mlp": "s", "pod": "^", "full_order": "D", "opinf": "v", "opinf_observed": "<"}

COMMON = ["logger=csv", "evaluation.every_n_epochs=0", "evaluation.figures=0", "trainer.enable_progress_bar=false"]
# Reduced settings (each study under 30 min on 2 CPU cores): smaller SIREN, 15 epochs, higher lr
REDUCED_NEURAL = ["model.width=64", "model.hyper_width=64", "trainer.max_epochs=15", "optimizer.lr=2e-3"]
SMOKE_DATA = ["data.n_train=3", "data.n_val=1", "data.n_test=2", "data.n_times=20", "data.train_times=10",
              "data.fine_resolution=12", "data.coarse_resolution=16", "data.batch_size=8"]
SMOKE_NEURAL = ["model.width=16", "model.hyper_width=8", "trainer.max_epochs=1", "quadrature.order=4",
                "evaluation.max_reduction_points=64"]


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
    rows: list[dict[str, Any]] = field(default_factory=list)
    started: float = field(default_factory=time.perf_counter)
    _scene: Any = field(default=None, init=False, repr=False, compare=False)

    # -- settings -------------------------------------------------------------------------------
    def base(self) -> list[str]:
        """Overrides shared by every training job of the study."""
        out = [f"+experiment={self.scene}", *COMMON, f"threads={self.threads}"]
        if self.mode == "smoke":
            out += SMOKE_DATA + ["evaluation.long_steps=10", "evaluation.long_trajectories=1"]
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
        return [*over, *extra]

    def unused_experiment_keys(self, node: str, config: str) -> list[str]:
        """Keys of the scene experiment's `node` (e.g. a SIREN width under `model`) that `config` (e.g.
        model/pod) does not have: they are deleted, since `+experiment=<scene>` merges them into any choice."""
        from omegaconf import OmegaConf

        own = OmegaConf.load(config_file(config, self.config_dir))
        return sorted(set(self.experiment().get(node) or {}) - set(own))

    def experiment(self) -> Any:
        """The scene's experiment config, ``experiment/<scene>.yaml`` of conf/ or of the config dir, as written
        (not composed)."""
        from omegaconf import OmegaConf

        return OmegaConf.load(experiment_file(self.scene, self.config_dir))

    def hydra_args(self) -> list[str]:
        """``--config-dir DIR`` for `python -m lnf.train` and `python -m lnf.evaluate` (none without a config dir)."""
        return [] if self.config_dir is None else ["--config-dir", str(self.config_dir)]

    def composed(self) -> Any:
        """The training config as `python -m lnf.train [--config-dir DIR] +experiment=<scene>` composes it, with its
        `hydra` node (`hydra.runtime.choices` names the option chosen in each config group)."""
        from hydra import compose, initialize_config_dir

        overrides = [f"+experiment={self.scene}"]
        if self.config_dir is not None:  # what --config-dir does: the folder is searched after conf/
            overrides.append(f"hydra.searchpath=['file://{self.config_dir}']")
        with initialize_config_dir(str(CONF), version_base=None):
            return compose("train", overrides=overrides, return_hydra_config=True)

    def scene_object(self) -> Any:
        """The scene of the study's experiment (a :class:`lnf.scenes.Scene`), built once from the composed
        config: what the study asks what the scene can do."""
        if self._scene is None:
            from omegaconf import OmegaConf

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
        mode = "" if self.mode == "reduced" else f" --{self.mode}"
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
        if stamp.is_file() and json.loads(stamp.read_text()) == cmd[1:] and _all_done(folder) and not self.fresh:
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
            _write_json_atomic(stamp, cmd[1:])
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


class JobWorker:
    """One Python process, started in the repository root with :func:`job_environment` (and the root first on
    PYTHONPATH, :func:`root_on_pythonpath`), that runs the study's multiruns one after another as
    `python -m <entry> <args>` would (``runpy`` runs the entry module as ``__main__``), each with its output in its
    own log file.

    Hydra already runs a multirun's jobs one after another in one process; the worker does the same across the
    multiruns of a study, so that torch, Lightning and Hydra are imported once (about 5 s a process on 2 cores)
    instead of once per multirun. A multirun that fails ends the worker; the next one starts a fresh one. So does
    a source file the worker has loaded (lnf's, your scene's) that changed after it started: it would otherwise mix
    the old modules with the new entry module."""

    def __init__(self) -> None:
        # the repository root, its folder and first on PYTHONPATH, imports this checkout's experiments and lnf
        loop = f"from experiments import studylib; studylib._worker_loop(parent={os.getpid()})"
        self.proc = subprocess.Popen([sys.executable, "-c", loop],
                                     cwd=ROOT, env=root_on_pythonpath(job_environment()), stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def run(self, entry: str, args: Sequence[str], log: Path) -> Optional[int]:
        """Run `python -m <entry> <args>` in the worker, its output into `log`; returns its exit status, or None
        when the worker found its sources changed (it has ended: run it in a fresh one)."""
        self.proc.stdin.write(json.dumps({"module": entry, "args": list(args), "log": str(log)}) + "\n")
        self.proc.stdin.flush()
        reply = self.proc.stdout.readline()
        if not reply:  # the worker died (killed, out of memory): its exit status
            self.proc.wait()
            return self.proc.returncode or 1
        answer = json.loads(reply)
        if answer.get("stale"):
            self.close()
            return None
        code = int(answer["returncode"])
        if code != 0:
            self.close()
        return code

    def close(self) -> None:
        if self.alive():
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


_WORKER: Optional[JobWorker] = None


def _worker() -> JobWorker:
    """The process's job worker, started on first use (and again after it ended)."""
    global _WORKER
    if _WORKER is None or not _WORKER.alive():
        import atexit

        if _WORKER is None:
            atexit.register(lambda: _WORKER is not None and _WORKER.close())
        _WORKER = JobWorker()
    return _WORKER


def run_in_worker(entry: str, args: Sequence[str], log: Path) -> int:
    """`python -m <entry> <args>` run by the job worker (a fresh one if its sources changed), its output in `log`;
    its exit status."""
    for _ in range(3):
        code = _worker().run(entry, args, log)
        if code is not None:
            return code
    raise RuntimeError(f"python -m {entry}: the source files keep changing while the study starts its job worker")


def _sources_changed(since: float, entry: str) -> bool:
    """Whether a module file the worker has loaded from outside the Python installation (lnf's, a scene's), or the
    entry module's file, changed after `since` (time.time())."""
    import importlib.util
    import sysconfig

    installed = tuple({sysconfig.get_paths()[key] for key in ("stdlib", "platstdlib", "purelib", "platlib")})
    spec = importlib.util.find_spec(entry)
    files = [getattr(module, "__file__", None) for module in list(sys.modules.values())]
    for path in [*files, spec.origin if spec else None]:
        if path and not path.startswith(installed):
            try:
                if os.stat(path).st_mtime > since:
                    return True
            except OSError:  # a file that has gone: the module stays as it was loaded
                continue
    return False


def _exit_with(parent: int, every: float = 1.0) -> None:
    """End this process as soon as `parent` (a pid) is no longer its parent: a study killed mid-job must not leave
    its worker training on (it would be adopted by init and hold the CPU for the rest of the job)."""
    import threading

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(every)
        os._exit(1)  # the job's files are written by temporary name and rename: nothing is left half-written

    threading.Thread(target=watch, name="lnf-worker-parent-watch", daemon=True).start()


def _worker_loop(parent: Optional[int] = None) -> None:
    """The worker's side of :class:`JobWorker`: one JSON request a line on stdin ({"module", "args", "log"}), one
    reply a line ({"returncode"}, or {"stale": true} and the worker ends) on the stdout it started with; file
    descriptors 1 and 2 go to the request's log while it runs, to /dev/null between requests. With `parent` (the
    study's pid) it ends when that process has gone, even in the middle of a job."""
    import runpy
    import traceback

    if parent is not None:
        _exit_with(parent)

    from hydra.core.global_hydra import GlobalHydra

    started = time.time()
    reply = os.fdopen(os.dup(1), "w")
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    for line in sys.stdin:
        request = json.loads(line)
        if _sources_changed(started, request["module"]):
            reply.write(json.dumps({"stale": True}) + "\n")
            reply.flush()
            return
        log = os.open(request["log"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(log, 1)
        os.dup2(log, 2)
        os.close(log)
        sys.argv = [request["module"], *request["args"]]
        code = 0
        try:
            GlobalHydra.instance().clear()
            runpy.run_module(request["module"], run_name="__main__", alter_sys=True)
        except SystemExit as exit_:
            code = exit_.code if isinstance(exit_.code, int) else 0 if exit_.code is None else 1
        except BaseException:  # noqa: BLE001 - reported in the log, and as the exit status
            traceback.print_exc()
            code = 1
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(null, 1)
        os.dup2(null, 2)
        reply.write(json.dumps({"returncode": code}) + "\n")
        reply.flush()


def default_experiment() -> str:
    """The experiment a study runs without ``--scene``: the one named like the default ``scene`` of the training
    config (conf/train.yaml), i.e. what ``python -m lnf.train`` trains without overrides."""
    from omegaconf import OmegaConf

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


def absolute_pythonpath(value: str) -> str:
    """A PYTHONPATH value with each relative entry made absolute against the current folder (the study's jobs run
    in the repository root, where a relative entry would name another folder)."""
    return os.pathsep.join(str(Path(p).resolve()) for p in value.split(os.pathsep))  # "" (the current folder) too


def job_environment() -> dict[str, str]:
    """The environment of the study's jobs, which run in the repository root: this one, with the caller's
    relative PYTHONPATH entries and LNF_DATA_DIR made absolute (against the caller's folder), LNF_ROOT = the
    repository root and full Hydra errors."""
    env = {**os.environ, "HYDRA_FULL_ERROR": "1", "LNF_ROOT": str(ROOT)}
    if env.get("PYTHONPATH"):
        env["PYTHONPATH"] = absolute_pythonpath(env["PYTHONPATH"])
    if env.get("LNF_DATA_DIR"):
        env["LNF_DATA_DIR"] = str(Path(env["LNF_DATA_DIR"]).resolve())
    return env


def root_on_pythonpath(env: dict[str, str]) -> dict[str, str]:
    """`env` with the repository root first on its PYTHONPATH (the entries it had kept after it): a Python process
    started with it imports this checkout's `experiments` package and lnf from any folder."""
    rest = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p and p != str(ROOT)]
    return {**env, "PYTHONPATH": os.pathsep.join([str(ROOT), *rest])}


def _shown(path: Path) -> str:
    """`path` as a command run from the repository root names it: relative inside the repository, else absolute."""
    path = Path(path).resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def parse_args(name: str, description: str, argv: Optional[Sequence[str]] = None,
               extra: Optional[callable] = None) -> tuple[Study, argparse.Namespace]:
    """The study's command line: ``--config-dir``, ``--scene``, ``--full``/``--smoke``, ``--out``, ``--threads``,
    ``--fresh`` and the study's own options (`extra` adds them to the parser)."""
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
    if extra is not None:
        extra(p)
    args = p.parse_args(argv)
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
                  config_dir=config_dir, one_process=not args.fresh_processes)
    try:
        scene = study.scene_object()
    except (ImportError, ValueError) as err:  # a module not on PYTHONPATH, a bad scene parameter
        p.error(f"--scene {args.scene}: its scene cannot be built: {err}")
    if not scene.capabilities()["simulator"]:
        p.error(f"--scene {args.scene}: scene {type(scene).__qualname__} has no simulator (simulate() and "
                f"sample_initial_states()); the studies generate each mode's dataset with it and re-simulate the "
                f"reference at other times, grids and initial states")
    return study, args


# ---------------------------------------------------------------------------------------------------
# results
# ---------------------------------------------------------------------------------------------------
def _job_dirs(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))


def keep_aside(folder: Path) -> Path:
    """Rename `folder` to `<name>.replaced-<UTC time>[-n]` beside it, so that a rerun never deletes results (a sweep
    run from another checkout, with other settings, or interrupted); returns the new path."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    target, n = folder.with_name(f"{folder.name}.replaced-{stamp}"), 1
    while target.exists():
        target, n = folder.with_name(f"{folder.name}.replaced-{stamp}-{n}"), n + 1
    folder.rename(target)
    return target


def _all_done(folder: Path) -> bool:
    jobs = _job_dirs(folder) if folder.is_dir() else []
    return bool(jobs) and all((j / "metrics.json").is_file() for j in jobs)


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def collect(folder: Path, sweep: str, label: Optional[dict[str, Any]] = None) -> list[dict[str, Any]]:
    """One row per finished job: sweep, job, its command-line overrides (key=value) and its metrics."""
    import yaml

    rows = []
    for job in _job_dirs(folder):
        metrics_file = job / "metrics.json"
        if not metrics_file.is_file():
            continue
        over = {}
        ofile = job / ".hydra" / "overrides.yaml"
        if ofile.is_file():
            for item in yaml.safe_load(ofile.read_text()) or []:
                key, _, value = str(item).partition("=")
                over[key.lstrip("+")] = _parse_value(value)
        rows.append({"sweep": sweep, "job": int(job.name), "dir": str(job.relative_to(ROOT) if job.is_relative_to(ROOT)
                                                                       else job),
                     **(label or {}), **over, **json.loads(metrics_file.read_text())})
    return rows


def _write_json_atomic(path: Path, payload: Any) -> None:
    """JSON written to a temporary name in the same folder, then renamed."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(payload, indent=1))
    os.replace(tmp, path)


def write_csv(path: Path, rows: list[dict[str, Any]]) -> Path:
    """All rows (union of keys; empty where a row lacks one), written to a temporary name, then renamed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    os.replace(tmp, path)
    return path


def method_of(row: dict[str, Any]) -> str:
    if row.get("method"):
        return row["method"]
    if row.get("dynamics") == "latent_mlp":
        return "latent_mlp"
    return {"pod": "pod", "full_order": "full_order"}.get(row.get("model"), "lnf")


def pareto_mask(cost: np.ndarray, error: np.ndarray) -> np.ndarray:
    """True where no other point has both lower-or-equal cost and error (and one strictly lower)."""
    cost, error = np.asarray(cost, float), np.asarray(error, float)
    ok = np.isfinite(cost) & np.isfinite(error)
    mask = np.zeros(len(cost), bool)
    for i in np.flatnonzero(ok):
        dominated = ok & (cost <= cost[i]) & (error <= error[i]) & ((cost < cost[i]) | (error < error[i]))
        mask[i] = not dominated.any()
    return mask


def dominates(front_cost: np.ndarray, front_error: np.ndarray, cost: float, error: float) -> bool:
    """Whether some point of a front has cost ≤ `cost` and error ≤ `error`."""
    return bool(np.any((np.asarray(front_cost) <= cost) & (np.asarray(front_error) <= error)))


# ---------------------------------------------------------------------------------------------------
# charts: labels in words, legends outside the data, labels that do not overlap, vector output
# ---------------------------------------------------------------------------------------------------
#: what a metric measures, in words, and its unit ("" where it has none): the first part of a metric key
#: ``<quantity>/<subset>/<statistic>`` (docs/method.md §7.3), or a whole key without slashes
QUANTITY_WORDS: dict[str, tuple[str, str]] = {
    "field_rel_l2": ("relative L² field error", ""),
    "projection_rel_l2": ("relative L² error of the projected field", ""),
    "latent_rmse": ("latent RMSE", ""),
    "energy_rel_err": ("energy error max_t |Ẽ − E| / E_scale", ""),
    "energy_drift": ("energy drift max_t |Ẽ(t) − Ẽ(0)| / E_scale", ""),
    "energy_drift_long": ("energy drift max_t |Ẽ(t) − Ẽ(0)| / E_scale (long run)", ""),
    "vpt": ("valid prediction time", "s"),
    "rollout_seconds_per_trajectory": ("latent rollout wall-clock per trajectory", "s"),
    "rollout_seconds_per_step": ("latent rollout wall-clock per step", "s"),
    "decode_seconds_per_trajectory": ("decoding wall-clock per trajectory", "s"),
    "fields_seconds_per_trajectory": ("rollout + decoding wall-clock per trajectory", "s"),
    "cost_seconds": ("rollout + decoding wall-clock per trajectory", "s"),
    "train_seconds": ("training wall-clock", "s"),
    "evaluation_seconds": ("evaluation wall-clock", "s"),
    "rollout_seconds": ("rollout wall-clock", "s"),
    "decode_seconds": ("decoding wall-clock", "s"),
    "total_seconds": ("rollout + decoding wall-clock", "s"),
    "rollout_peak_mib": ("peak memory of the rollout above baseline", "MiB"),
    "decode_peak_mib": ("peak memory of the decoding above baseline", "MiB"),
    "peak_mib": ("peak memory above baseline", "MiB"),
    "points": ("evaluation points", ""),
    "batch": ("trajectories rolled out at once", ""),
    "flops": ("matmul FLOPs of one RK4 step", ""),
    "seconds": ("measured time of one RK4 step", "s"),
    "bound_seconds": ("FLOP bound of one RK4 step", "s"),
    "ratio": ("measured time / FLOP bound", ""),
    "gflops_achieved": ("achieved matmul throughput", "GFLOP/s"),
    "diverged_fraction": ("share of diverged test rollouts", ""),
    # sweep settings
    "model.width": ("SIREN width (neurons per hidden layer)", ""),
    "model.latent_dim": ("latent dimension d", ""),
    "model.depth": ("SIREN depth (hidden layers)", ""),
    "model.reduction_steps": ("reduction steps K", ""),
    "model.resolution": ("full-order grid points per axis", ""),
    "data.observed_fraction": ("observed share of the coarse training grid", ""),
    "data.noise": ("observation noise (std / RMS of the observed values)", ""),
    "dt": ("time step dt", "s"),
    "quadrature.order": ("Gauss–Legendre points per axis", ""),
    "quadrature.resolution": ("uniform quadrature points per axis", ""),
}
SUBSET_WORDS = {"all": "", "in_horizon": "within the training horizon", "extrapolation": "after the training horizon"}
STATISTIC_WORDS = {"median": "median", "max": "max", "min": "min", "mean": "mean"}


def metric_label(key: str, split: str = "test", over: str = "trajectories", wrap: bool = False) -> str:
    """A metric key (``field_rel_l2/extrapolation/median``, ``train_seconds``, ``model.width``) in words with its
    unit, as an axis label: "relative L² field error after the training horizon (test, median over
    trajectories)", "training wall-clock [s]". `split` names the trajectories a ``<quantity>/<subset>/<stat>``
    metric is taken on, `over` what its statistic runs over; `wrap` breaks the line before the parenthesis. A key
    the table does not know is returned as it is."""
    parts = key.split("/")
    words, unit = QUANTITY_WORDS.get(parts[0], (None, ""))
    if words is None:
        return key
    subset = SUBSET_WORDS.get(parts[1], parts[1]) if len(parts) == 3 else ""
    stat = STATISTIC_WORDS.get(parts[-1], parts[-1]) if len(parts) >= 2 else ""
    text = words + (f" {subset}" if subset else "")
    detail = ", ".join(p for p in (split if len(parts) >= 2 else "", f"{stat} over {over}" if stat else "") if p)
    units = f" [{unit}]" if unit else ""
    if detail:
        return f"{text}{units}" + ("\n" if wrap else " ") + f"({detail})"
    return f"{text}{units}"


def save_figure(fig: Any, path: Path) -> Path:
    """The figure as a PNG (200 dpi) and a vector PDF of the same stem beside it (``pareto.png`` and
    ``pareto.pdf``), each written atomically by :func:`lnf.plotting.save_figure` and cropped to its content;
    returns the PNG's path and closes the figure."""
    import matplotlib.pyplot as plt

    from lnf.plotting import save_figure as save_png_and_pdf

    try:
        return save_png_and_pdf(fig, path, bbox_inches="tight")
    finally:
        plt.close(fig)


#: line styles that keep coincident curves apart (with the method's marker and colour)
LINESTYLES = {"lnf": "-", "latent_mlp": "--", "pod": "-.", "full_order": ":", "opinf": (0, (3, 1, 1, 1, 1, 1)),
              "opinf_observed": (0, (1, 1))}
#: where each method's curve sits in a small sideways dodge (steps of DODGE_FRACTION of the x range)
DODGE = {"lnf": -1.5, "latent_mlp": -0.5, "pod": 0.5, "full_order": 1.5, "opinf": 2.5, "opinf_observed": 3.5}
DODGE_FRACTION = 0.012
DODGE_NOTE = "curves drawn slightly apart in x (a few % of the axis at most) so that equal values stay visible"


def dodged(x: Any, method: str, log: bool = True, steps: Optional[float] = None) -> np.ndarray:
    """x moved sideways by `steps` (default ``DODGE[method]``) × DODGE_FRACTION of its range (in decades on a log
    axis, at least half a decade; linear: of its span), so that curves of several methods with equal values stay
    visible side by side. Ticks stay at the true values (:func:`ticks_at`)."""
    x = np.asarray(x, dtype=float)
    c = DODGE.get(method, 0.0) if steps is None else float(steps)
    fin = x[np.isfinite(x) & (x > 0)] if log else x[np.isfinite(x)]
    if log:
        span = max(float(np.log10(fin.max() / fin.min())), 0.5) if fin.size else 0.5
        return x * 10.0 ** (c * DODGE_FRACTION * span)
    span = float(np.ptp(fin)) if fin.size > 1 else 0.0
    return x + c * DODGE_FRACTION * (span if span > 0 else max(float(np.abs(fin).max()) if fin.size else 1.0, 1e-12))


def plot_marking_failures(ax: Any, x: np.ndarray, y: np.ndarray, failed: np.ndarray, *fmt: str, **kwargs: Any) -> None:
    """Line of y against x where non-finite or `failed` points are drawn at 10 and marked × (in the line's
    colour, black edge). The line is slightly transparent (alpha 0.85 unless given) and its markers are hollow-
    edged, so that a curve on top of another leaves it visible."""
    failed = np.asarray(failed, bool) | ~np.isfinite(y)
    yy = np.where(np.isfinite(y), y, 10.0)
    kwargs.setdefault("alpha", 0.85)
    kwargs.setdefault("markersize", 6)
    kwargs.setdefault("markeredgecolor", "white")
    kwargs.setdefault("markeredgewidth", 0.6)
    (line,) = ax.plot(x, yy, *fmt, **kwargs)
    if failed.any():
        ax.scatter(x[failed], yy[failed], marker="X", s=70, color=line.get_color(), edgecolors="k", linewidths=0.6,
                   zorder=4)


def legend_outside(ax: Any, where: str = "right", fontsize: float | str = "small", **kwargs: Any) -> Any:
    """The legend of `ax` outside its data: to the right of the axes (``where="right"``) or under its x label
    (``"below"``, several columns; set the x label first: the legend starts as far below the axes as the tick
    labels and the label's lines reach). Constrained layout (or ``bbox_inches="tight"``) makes room for it."""
    if where == "below":
        import matplotlib as mpl
        from matplotlib.font_manager import FontProperties
        from matplotlib.transforms import offset_copy

        rc = mpl.rcParams
        size = lambda key: FontProperties(size=rc[key]).get_size_in_points()  # noqa: E731
        label = ax.get_xlabel()
        lines = label.count("\n") + 1 if label else 0
        drop = (rc["xtick.major.size"] + rc["xtick.major.pad"] + 1.3 * size("xtick.labelsize")
                + (rc["axes.labelpad"] + 1.25 * size("axes.labelsize") * lines if lines else 0) + 3.0)
        below = offset_copy(ax.transAxes, fig=ax.figure, x=0.0, y=-drop, units="points")
        kwargs.setdefault("ncols", 2)
        return ax.legend(loc="upper center", bbox_to_anchor=(0.5, 0.0), bbox_transform=below, fontsize=fontsize,
                         frameon=False, borderaxespad=0.0, **kwargs)
    return ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, fontsize=fontsize,
                     frameon=False, **kwargs)


def figure_legend(fig: Any, axes: Sequence[Any], ncols: int = 4, fontsize: float | str = "small", **kwargs: Any) -> Any:
    """One legend for all `axes` (entries with the same label once), below the panels, outside the data (the
    figure must use constrained layout)."""
    handles: dict[str, Any] = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if not lab.startswith("_"):
                handles.setdefault(lab, h)
    if not handles:
        return None
    return fig.legend(list(handles.values()), list(handles), loc="outside lower center", fontsize=fontsize,
                      ncols=min(ncols, len(handles)), frameon=False, **kwargs)


def readable_log_ticks(ax: Any, decades: float = 2.5) -> None:
    """Tick labels of the log axes of `ax` that do not run into each other: no minor tick labels (matplotlib labels
    2×10⁻¹, 3×10⁻¹, … on a short log axis, which collide on a narrow panel); an axis spanning fewer than `decades`
    decades gets its major ticks at 1, 2 and 5 × 10^k, written plainly ("0.2", "5"). Call it once the data are
    drawn (it reads the limits); an axis with ticks of its own (:func:`ticks_at`) is left as it is."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, LogFormatterSciNotation, LogLocator, NullFormatter

    for name in ("x", "y"):
        axis = getattr(ax, f"{name}axis")
        if axis.get_scale() != "log" or isinstance(axis.get_major_locator(), FixedLocator):
            continue
        base = getattr(axis.get_transform(), "base", 10.0)
        lo, hi = sorted(getattr(ax, f"get_{name}lim")())
        if base == 10 and lo > 0 and np.log10(hi / lo) < decades:
            axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        else:  # (again: a shared axis may have been narrower at an earlier call)
            axis.set_major_locator(LogLocator(base=base))
            axis.set_major_formatter(LogFormatterSciNotation(base=base))
        axis.set_minor_formatter(NullFormatter())


def log_axes(ax: Any, legend_size: float | str = "small", x_base: float = 10, legend: str = "right") -> None:
    """Log–log axes with a light grid, readable tick labels (:func:`readable_log_ticks`; call it after drawing the
    data) and a legend outside the data (`legend`: "right", "below", or "none")."""
    ax.set_xscale("log", base=x_base)
    ax.set_yscale("log")
    ax.grid(True, which="major", alpha=0.35)
    ax.grid(True, which="minor", alpha=0.12)
    readable_log_ticks(ax)
    if legend != "none":
        legend_outside(ax, legend, fontsize=legend_size)


def _line_samples(ax: Any, step_px: float) -> np.ndarray:
    """Points every `step_px` pixels along the lines of `ax` (steps drawn as steps, axvlines included), (n, 2)
    in display coordinates: labels must not sit on them."""
    from matplotlib import cbook

    out = [np.zeros((0, 2))]
    for line in ax.get_lines():
        xy = np.asarray(line.get_xydata(), dtype=float)
        if len(xy) == 0 or line.get_linestyle() in ("None", "none", "", " "):
            continue
        style = line.get_drawstyle()
        if style and style.startswith("steps") and len(xy) > 1:
            xy = np.column_stack(cbook.STEP_LOOKUP_MAP[style](xy[:, 0], xy[:, 1]))
        with np.errstate(all="ignore"):
            d = line.get_transform().transform(xy)
        d = d[np.all(np.isfinite(d), axis=1)]
        for p, q in zip(d[:-1], d[1:]):
            n = max(2, int(np.hypot(*(q - p)) / step_px) + 1)
            out.append(p + np.linspace(0.0, 1.0, n)[:, None] * (q - p))
    return np.concatenate(out)


def ticks_at(ax: Any, values: Iterable[Any], axis: str = "x", fmt: Any = None) -> None:
    """Major ticks of `axis` at the (positive, finite) `values` a sweep took, labelled plainly ("0.05", "64";
    `fmt(value)` for another text), no minor tick labels: a log axis of a few settings reads as those settings,
    not as 2×10⁻¹, 3×10⁻¹ ... labels that run into each other."""
    from matplotlib.ticker import NullFormatter

    vals = []
    for v in values:
        try:
            v = float(v)
        except (TypeError, ValueError):
            continue
        if np.isfinite(v) and v > 0 and v not in vals:
            vals.append(v)
    if not vals:
        return
    vals.sort()
    getattr(ax, f"set_{axis}ticks")(vals, [fmt(v) if fmt else f"{v:g}" for v in vals])
    getattr(ax, f"{axis}axis").set_minor_formatter(NullFormatter())


def place_labels(ax: Any, xs: Sequence[float], ys: Sequence[float], texts: Sequence[str], fontsize: float = 7,
                 avoid: Sequence[tuple[float, float]] = (), pad_points: float = 2.5) -> list[Any]:
    """Annotate the points (xs[i], ys[i]) (data coordinates) with texts[i], each placed greedily at the first of
    a ring of offsets around its point (near first, then farther, with a thin leader line) whose box overlaps
    neither a label placed before, nor a marker (the points themselves and `avoid`), nor a line of the axes, nor
    its edge. A label that fits nowhere is left out. Measured with the figure's renderer after its layout is
    done: call it once the axes' limits, scales and the figure's legends are final (the labels themselves are
    kept out of the layout). Returns the annotations drawn."""
    from lnf.plotting import _DPI

    fig = ax.figure
    dpi = fig.dpi
    fig.set_dpi(_DPI)  # measured at the PNG's resolution: text widths vary a little with the dpi (hinting)
    try:
        return _place_labels(ax, xs, ys, texts, fontsize, avoid, pad_points)
    finally:
        fig.set_dpi(dpi)


def _place_labels(ax: Any, xs: Sequence[float], ys: Sequence[float], texts: Sequence[str], fontsize: float,
                  avoid: Sequence[tuple[float, float]], pad_points: float) -> list[Any]:
    fig = ax.figure
    fig.draw_without_rendering()  # the final layout and limits: positions below are those of the saved figure
    renderer = fig.canvas.get_renderer()
    to_px = fig.dpi / 72.0
    frame = ax.get_window_extent(renderer)
    marker_pt = 4.5  # half a marker's size [points]
    r = marker_pt * to_px
    with np.errstate(all="ignore"):  # a point a log axis cannot show is no obstacle
        pts = np.array([ax.transData.transform((float(x), float(y))) for x, y in list(zip(xs, ys)) + list(avoid)]
                       ).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    lines = _line_samples(ax, 2.0 * to_px)
    lw = 1.0 * to_px
    boxes = np.concatenate([np.column_stack([pts - r, pts + r]), np.column_stack([lines - lw, lines + lw])])
    out = []
    rings = [(1.0, False), (1.8, True), (2.8, True)]
    dirs = [(1, 1), (1, -1), (-1, 1), (-1, -1), (1, 0), (-1, 0), (0, 1), (0, -1)]
    for x, y, text in zip(xs, ys, texts):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        placed = None
        for scale, leader in rings:
            for dx, dy in dirs:
                off = (dx * (marker_pt + pad_points) * scale, dy * (marker_pt + pad_points) * scale)
                ha = {1: "left", -1: "right", 0: "center"}[dx]
                va = {1: "bottom", -1: "top", 0: "center"}[dy]
                ann = ax.annotate(text, (x, y), xytext=off, textcoords="offset points", ha=ha, va=va,
                                  fontsize=fontsize, annotation_clip=True, zorder=6,
                                  bbox=dict(boxstyle="square,pad=0.1", facecolor="white", alpha=0.7, linewidth=0),
                                  arrowprops=dict(arrowstyle="-", lw=0.5, color="0.4", shrinkA=0, shrinkB=3)
                                  if leader else None)
                ann.set_in_layout(False)
                b = ann.get_window_extent(renderer)
                inside = frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 and b.y1 <= frame.y1
                hit = (boxes[:, 0] < b.x1) & (boxes[:, 2] > b.x0) & (boxes[:, 1] < b.y1) & (boxes[:, 3] > b.y0)
                if inside and not hit.any():
                    placed = ann
                    pad = 0.5 * fontsize * to_px  # labels keep apart by half an em
                    boxes = np.vstack([boxes, [b.x0 - pad, b.y0 - pad, b.x1 + pad, b.y1 + pad]])
                    break
                ann.remove()
            if placed is not None:
                break
        if placed is not None:
            out.append(placed)
    return out


def caption(study: Study) -> str:
    return f"{study.command()} · {study.mode} settings · {study.machine()}"


def per_axis(n: Any, dim: int) -> str:
    """`n` per axis of a `dim`-D body as charts and summaries write it: "8²" in 2-D, "8³" in 3-D, "8" in 1-D."""
    return f"{n}" + {1: "", 2: "²", 3: "³"}.get(dim, f"^{dim}")


def fmt(x: Any, digits: int = 3) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not np.isfinite(x):
        return "diverged"  # metrics of a rollout that left the finite range are NaN or inf
    return f"{x:.{digits}g}"


def markdown_table(rows: list[dict[str, Any]], columns: list[tuple[str, str]]) -> str:
    """Rows as a Markdown table; columns are (key, header)."""
    head = "| " + " | ".join(h for _, h in columns) + " |\n|" + "---|" * len(columns) + "\n"
    return head + "".join("| " + " | ".join(fmt(r.get(k, "")) for k, _ in columns) + " |\n" for r in rows)


def write_text_atomic(path: Path, text: str) -> Path:
    """Text written to a temporary name in the same folder, then renamed (:func:`lnf.tempfiles.write_text_atomic`)."""
    from lnf.tempfiles import write_text_atomic as write

    return write(path, text)
