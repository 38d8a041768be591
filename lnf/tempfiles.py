"""Atomic writes through temporaries (``{name}.tmp-…-{pid}``), and telling a killed writer's leftovers from a live one's."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable


def writer_is_gone(pid: str) -> bool:
    """True when `pid` (the digits at the end of a temporary's name) names no running process on this host;
    False for a live process (ours, another's, another user's) and for a name that is not a pid."""
    if not pid.isdigit():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, another user's
        return False
    return False


def _replace_atomically(path: "str | Path", write: Callable[[Path], Any]) -> Path:
    """`write(tmp)` to a temporary name in the same folder (parents created), then rename it over `path`: a reader
    never sees a half-written file, and the temporary is removed whatever happens. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_text_atomic(path: "str | Path", text: str) -> Path:
    """`text` written to a temporary name in the same folder (parents created), then renamed over `path`: a reader
    never sees a half-written file, and the temporary is removed whatever happens. Returns the path."""
    return _replace_atomically(path, lambda tmp: tmp.write_text(text))


def write_bytes_atomic(path: "str | Path", data: bytes) -> Path:
    """`data` written as :func:`write_text_atomic` writes text. Returns the path."""
    return _replace_atomically(path, lambda tmp: tmp.write_bytes(data))


def write_json_atomic(path: "str | Path", payload: Any) -> Path:
    """`payload` as indented JSON with sorted keys, written as :func:`write_text_atomic` writes text."""
    return write_text_atomic(path, json.dumps(payload, indent=2, sort_keys=True))
