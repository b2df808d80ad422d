"""Process-tree helpers for the interruption tests (Linux /proc)."""

from __future__ import annotations

import time
from pathlib import Path

from core.runtime.parallel import descendants  # noqa: F401  (re-exported for the tests)


def alive(pid: int) -> bool:
    """Whether ``pid`` is a live process (not gone, not a zombie)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def still_alive(pids: set[int], guard: float = 10.0) -> list[int]:
    """The processes of ``pids`` still alive once they stopped, or after a hang guard
    (not a timing assertion: they are given their time to exit)."""
    deadline = time.monotonic() + guard
    while time.monotonic() < deadline and any(alive(p) for p in pids):
        time.sleep(0.05)
    return sorted(p for p in pids if alive(p))


def session_members(sid: int) -> list[int]:
    """Live processes of session ``sid`` (from /proc: no ``ps`` on a minimal system)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] not in ("Z", "X"):  # state, ppid, pgrp, session
            out.append(int(stat.parent.name))
    return sorted(out)
