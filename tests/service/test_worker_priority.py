"""The processes that train run niced (DROP_WORKER_NICE), so an API on the same machine gets the CPU first; the
worker's main process, which takes messages and reaps, keeps its own priority."""
from __future__ import annotations

import time

from .processes import children, niceness


def test_pool_processes_are_niced(worker, settings):
    assert settings.worker_nice == 10
    deadline = time.monotonic() + 30
    while not (pool := children(worker.pid)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert pool, "the worker has no pool process"
    own = niceness(worker.pid)  # the test run's own, which the worker inherited
    assert [niceness(pid) for pid in pool] == [min(19, own + settings.worker_nice)] * len(pool)
