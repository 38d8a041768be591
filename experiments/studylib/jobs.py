"""Running a study's jobs: the environment they run in (the repository root) and the worker process
(:class:`JobWorker`) that runs its multiruns one after another."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"


class JobWorker:
    """One Python process, started in the repository root with :func:`job_environment` (and the root first on
    PYTHONPATH), that runs the study's multiruns one after another as `python -m <entry> <args>` would (``runpy``
    runs the entry module as ``__main__``), each with its output in its own log file.

    Hydra already runs a multirun's jobs one after another in one process; the worker does the same across the
    multiruns of a study, so that torch, Lightning and Hydra are imported once (about 5 s a process on 2 cores)
    instead of once per multirun. A multirun that fails ends the worker; the next one starts a fresh one. So does
    a source file the worker has loaded (lnf's, your scene's) that changed after it started: it would otherwise mix
    the old modules with the new entry module."""

    def __init__(self) -> None:
        # the repository root, its folder and first on PYTHONPATH (the other entries kept after it), imports this
        # checkout's experiments and lnf
        env = job_environment()
        path = [str(ROOT), *(p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p and p != str(ROOT))]
        loop = f"from experiments.studylib import jobs; jobs._worker_loop(parent={os.getpid()})"
        self.proc = subprocess.Popen([sys.executable, "-c", loop], cwd=ROOT, stdin=subprocess.PIPE,
                                     env={**env, "PYTHONPATH": os.pathsep.join(path)}, stdout=subprocess.PIPE, text=True)

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


def run_in_worker(entry: str, args: Sequence[str], log: Path) -> int:
    """`python -m <entry> <args>` run by the process's job worker (started on first use, and afresh after it ended
    or found its sources changed), its output in `log`; its exit status."""
    global _WORKER
    for _ in range(3):
        if _WORKER is None or not _WORKER.alive():
            if _WORKER is None:
                import atexit

                atexit.register(lambda: _WORKER is not None and _WORKER.close())
            _WORKER = JobWorker()
        code = _WORKER.run(entry, args, log)
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
