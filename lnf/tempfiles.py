"""Temporaries of atomic writes (``{name}.tmp-…-{pid}``): telling a killed writer's leftovers from a live one's."""
from __future__ import annotations

import os


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
