"""One lnf run at a time in an output folder: a second one is refused, naming the first.

Two runs writing one folder would overwrite each other's checkpoints, logs and metrics (the CSV log of one was
lost, and both exited 0). :func:`run_folder_lock` takes an exclusive ``flock`` on ``{folder}/.lnf-run.lock``
for the duration of a run. The operating system releases it when the process ends, however it ends (kill -9
included), so a stale lock never blocks the next run. Only the first process of a distributed run takes it
(rank 0 by ``RANK``, ``LOCAL_RANK`` or ``SLURM_PROCID``): the others are the same run.
"""
from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: no advisory locks, runs are not serialised
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger("lnf.run_lock")

LOCK_NAME = ".lnf-run.lock"
EVALUATION_RESULTS = ("metrics.json", "run.json", "figures")  # what lnf.evaluate writes in its output folder
_HELD: dict[Path, int] = {}  # folders this process holds, and how many nested holders: the lock is re-entrant


class RunFolderBusyError(RuntimeError):
    """Another lnf run holds the output folder; the message names it and what to do."""


def _rank_zero() -> bool:
    return all(os.environ.get(k, "0") in ("", "0") for k in ("RANK", "LOCAL_RANK", "SLURM_PROCID"))


@contextmanager
def run_folder_lock(folder: "str | Path", command: str) -> Iterator[None]:
    """Hold `folder` for this process while the block runs; :class:`RunFolderBusyError` at once if another run
    holds it. `command` (e.g. "python -m lnf.train") is recorded in the lock file for that message."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    key = folder.resolve()
    if fcntl is None or not _rank_zero() or key in _HELD:  # held already by this process (its Hydra run, say)
        _HELD[key] = _HELD.get(key, 0) + 1
        try:
            yield
        finally:
            _HELD[key] -= 1
            if not _HELD[key]:
                del _HELD[key]
        return
    handle = open(folder / LOCK_NAME, "a+")
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.seek(0)
            holder = handle.read().strip() or "a process that did not say what it is"
            raise RunFolderBusyError(
                f"the output folder {folder} is in use by another lnf run ({holder}); two runs in one folder "
                f"would overwrite each other's checkpoints, logs and metrics. Wait for it to end, or give this "
                f"run a folder of its own (hydra.run.dir=...)") from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"{command}, process {os.getpid()} on {socket.gethostname()}, since "
                     f"{time.strftime('%Y-%m-%d %H:%M:%S %Z')}\n")
        handle.flush()
        _HELD[key] = 1
        try:
            yield
        finally:
            del _HELD[key]
    finally:
        handle.close()  # closing the file releases the lock


def set_aside(folder: Path, names: "tuple[str, ...]") -> "Path | None":
    """Move the entries `names` of `folder` that exist (an earlier run's files) to ``previous/<time>/`` beside
    them; nothing is deleted. Returns that folder, or None when there was nothing to move."""
    found = [folder / name for name in names if (folder / name).exists()]
    if not found:
        return None
    stamp = time.strftime("%Y-%m-%d_%H-%M-%S")
    dest, k = folder / "previous" / stamp, 1
    while dest.exists():
        dest, k = folder / "previous" / f"{stamp}_{k}", k + 1
    dest.mkdir(parents=True)
    for item in found:
        item.replace(dest / item.name)
    log.info("moved the results of an earlier run in %s (%s) to %s", folder, ", ".join(p.name for p in found), dest)
    return dest
