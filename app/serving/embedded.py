"""`drop serve` as one process tree: the API in this process, one worker in a child, started and stopped together.

This process owns the signals. SIGTERM, SIGINT and SIGHUP each stop the API, then the worker with a SIGTERM: Celery's
warm shutdown, in which the running job writes a checkpoint and goes back to the queue for the next `drop serve` to
resume. uvicorn's own handlers are kept out: they re-raise the signal once the API has stopped, which killed this
process before it could stop the worker, and that orphan went on taking jobs beside the next `drop serve`'s worker.
The worker runs in a session of its own, so a terminal's Ctrl-C reaches it once, from here, and not also directly (a
second signal is a cold shutdown to Celery); and it gets a SIGTERM when this process dies however it dies
(`procs.die_with_parent`), so it never outlives it.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
from typing import Iterator

import uvicorn

from .procs import SERVE_ENV

log = logging.getLogger("drop.serve")
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
WORKER_STOP_S = 60  # for the running job's final checkpoint; then the worker's process group is killed
STARTUP_FAILURE = 3  # uvicorn.run's exit status when the server could not start


class _Server(uvicorn.Server):
    """uvicorn's server without its signal handling: `serve` installs its own, for the whole tree."""

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        yield


def serve(config: uvicorn.Config) -> int:
    """Run the API with `config` and one worker until a stop signal; the exit status."""
    server = _Server(config)

    def stop(signum: int, frame) -> None:
        if server.should_exit:  # asked again: stop waiting for open connections and streams
            server.force_exit = True
        server.should_exit = True

    previous = {sig: signal.signal(sig, stop) for sig in STOP_SIGNALS}  # before the worker: no signal goes unheard
    try:
        worker = _start_worker()
        try:
            server.run()
        finally:
            _stop_worker(worker)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0 if server.started else STARTUP_FAILURE


def _start_worker() -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "app.cli", "worker", "--loglevel", "WARNING"],
                            env={**os.environ, SERVE_ENV: str(os.getpid())}, start_new_session=True)


def _stop_worker(worker: subprocess.Popen) -> None:
    """Warm shutdown, waited for; past WORKER_STOP_S the worker and its pool processes are killed."""
    log.info("stopping the worker: a running job writes a checkpoint and goes back to the queue")
    worker.send_signal(signal.SIGTERM)
    try:
        worker.wait(WORKER_STOP_S)
    except subprocess.TimeoutExpired:
        log.error("the worker did not stop within %s s; killing it", WORKER_STOP_S)
        os.killpg(worker.pid, signal.SIGKILL)
        worker.wait()
