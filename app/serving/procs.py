"""Tie child processes to the process that started them, so none outlives it as an orphan: the processes of `drop api
--workers N` would keep serving (and holding) the port, `drop serve`'s worker would keep taking jobs."""
from __future__ import annotations

import ctypes
import os
import signal
import sys

SUPERVISOR_ENV = "DROP_API_SUPERVISOR_PID"
SERVE_ENV = "DROP_SERVE_PID"
PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int, sig: signal.Signals) -> None:
    """`sig` to this process when its parent exits (Linux; a no-op elsewhere)."""
    if not sys.platform.startswith("linux"):
        return
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, sig)
    if os.getppid() != parent_pid:  # the parent died before the line above
        os.kill(os.getpid(), sig)


def supervised() -> None:
    """In a worker process of `drop api --workers N`: die with the supervisor that started it. SIGKILL, not SIGTERM: an
    API process holds nothing that needs a clean stop, and a graceful one would keep serving its open streams
    meanwhile."""
    parent = os.environ.get(SUPERVISOR_ENV)
    if parent:
        die_with_parent(int(parent), signal.SIGKILL)


def serve_worker() -> None:
    """In `drop serve`'s worker: a SIGTERM, so a warm shutdown that checkpoints and re-queues the running job, when
    `drop serve` dies without stopping it (killed, say). Read once: the pool processes must not inherit it."""
    parent = os.environ.pop(SERVE_ENV, None)
    if parent:
        die_with_parent(int(parent), signal.SIGTERM)
