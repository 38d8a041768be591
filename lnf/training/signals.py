"""SIGTERM ends a run wherever it is.

Lightning replaces the SIGTERM handler with one that only sets a flag its training loops read: a run in its test
rollouts (or in a validation callback) went on for as long as they took, and ``kill <pid>`` seemed not to work.
:func:`ended_by_sigterm` installs a handler that raises ``SystemExit(143)``; Lightning keeps an existing handler
and calls it after its own, so the run stops (its lock released, its results not written). Under SLURM
(``SLURM_JOB_ID`` set) the signal stays Lightning's, whose auto-requeue relies on it.
"""
from __future__ import annotations

import contextlib
import os
import signal
import threading
from typing import Iterator


@contextlib.contextmanager
def ended_by_sigterm() -> Iterator[None]:
    """Within the block, SIGTERM raises SystemExit(128 + SIGTERM); the previous handler is restored after it. A no-op
    off the main thread (only it may set handlers) and under SLURM."""
    if os.environ.get("SLURM_JOB_ID") or threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
