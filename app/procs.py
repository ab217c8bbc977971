"""Tie the processes of `drop api --workers N` to their supervisor: killed, it must not leave orphans that keep
serving (and holding) the port, so each worker process dies with it."""
from __future__ import annotations

import ctypes
import os
import signal
import sys

SUPERVISOR_ENV = "DROP_API_SUPERVISOR_PID"
PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int) -> None:
    """SIGKILL this process when its parent exits (Linux; a no-op elsewhere). SIGKILL, not SIGTERM: an API process
    holds nothing that needs a clean stop, and a graceful one would keep serving its open streams meanwhile."""
    if not sys.platform.startswith("linux"):
        return
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent_pid:  # the parent died before the line above
        os.kill(os.getpid(), signal.SIGKILL)


def supervised() -> None:
    """In a worker process of `drop api --workers N`: die with the supervisor that started it."""
    parent = os.environ.get(SUPERVISOR_ENV)
    if parent:
        die_with_parent(int(parent))
