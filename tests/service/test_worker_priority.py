"""The processes that train run niced (DROP_WORKER_NICE), so an API on the same machine gets the CPU first; the
worker's main process, which takes messages and reaps, keeps its own priority."""
from __future__ import annotations

import time

from .processes import children, niceness


def _pool_niceness(pid: int) -> list[int] | None:
    """The niceness of each pool process, or None while the pool is being replaced (one process per job: a new one
    is niced by its own start-up, a moment after it appears, and one that ends vanishes mid-read)."""
    try:
        return [niceness(child) for child in children(pid)] or None
    except (FileNotFoundError, ProcessLookupError):
        return None


def test_pool_processes_are_niced(worker, settings):
    assert settings.worker_nice == 10
    own = niceness(worker.pid)  # the test run's own, which the worker inherited
    expected = min(19, own + settings.worker_nice)
    deadline = time.monotonic() + 30
    while (pool := _pool_niceness(worker.pid)) is None or set(pool) != {expected}:
        if time.monotonic() >= deadline:
            break
        time.sleep(0.2)
    assert pool, "the worker has no pool process"
    assert pool == [expected] * len(pool)
