"""Keep freed memory in the process instead of returning it to the system (glibc only).

Training and decoding allocate and free the same 8–128 MiB activation buffers at every step. glibc serves
blocks that large with fresh ``mmap`` calls and returns them to the kernel when freed, so every step pays the
page faults of touching them again (measured: decoding 16 trajectories × 100 frames on the 64² grid ran
about 2× faster with this setting, `experiments/bench_training.py`). :func:`keep_freed_memory` turns that
off with ``mallopt``: no ``mmap`` for large blocks and no trimming of the heap, so freed buffers are reused.
The price is that the process keeps its peak heap until it exits.

The entry points (`lnf.train`, `lnf.evaluate`) call it; set ``LNF_KEEP_FREED_MEMORY=0`` to leave the
allocator as it is. In your own scripts, call ``lnf.allocator.keep_freed_memory()`` once at the start.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

_M_TRIM_THRESHOLD = -1  # glibc <malloc.h>
_M_MMAP_MAX = -4
_applied = False


def keep_freed_memory() -> bool:
    """Apply the setting once per process; True when it is in effect (glibc, not disabled by the environment)."""
    global _applied
    if _applied:
        return True
    if os.environ.get("LNF_KEEP_FREED_MEMORY", "1").strip().lower() in ("0", "false", "no", "off"):
        return False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl or another libc without mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _applied = bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))
    return _applied
