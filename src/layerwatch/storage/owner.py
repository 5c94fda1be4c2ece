"""Which process writes a job, and whether that process still runs.

A job row records its writer as ``{"host", "pid", "start"}`` where ``start``
is the process's start time in clock ticks since boot (``/proc/PID/stat``,
field 22), so a recycled process id is not mistaken for the writer. A job
whose writer is gone while its outcome is still empty was interrupted (the
process was killed or the machine lost power).
"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import Any

__all__ = ["this_process", "is_gone"]


def _start_ticks(pid: int) -> int | None:
    """Start time of ``pid`` in clock ticks after boot, or ``None`` without ``/proc`` or process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    # the command name (field 2) may hold spaces and parentheses: split after its closing one
    fields = stat.rsplit(")", 1)[-1].split()
    try:
        return int(fields[19])  # field 22 of the whole line
    except (IndexError, ValueError):
        return None


def this_process() -> dict[str, Any]:
    """The calling process as a job owner record ``{"host": str, "pid": int, "start": int | None}``."""
    pid = os.getpid()
    return {"host": socket.gethostname(), "pid": pid, "start": _start_ticks(pid)}


def is_gone(owner: dict[str, Any] | None) -> bool:
    """True when ``owner`` (a :func:`this_process` record) is a process on this host that no longer runs.

    Owners on other hosts (a database on a shared folder) and unknown owners
    (rows written before owners were recorded) are never judged gone.
    """
    if not isinstance(owner, dict) or owner.get("host") != socket.gethostname():
        return False
    pid = owner.get("pid")
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        pass  # alive, owned by another user
    start = owner.get("start")
    now = _start_ticks(pid)
    return start is not None and now is not None and now != start  # the id was recycled
