"""Celery entry points: the `drop.run_job` task and the reaper thread of each worker's main process."""
from __future__ import annotations

import logging
import os
import tempfile
import threading
from pathlib import Path

from celery.signals import setup_logging, worker_process_init, worker_ready, worker_shutdown, worker_shutting_down

from kernel.db import make_engine, make_sessionmaker
from kernel.queue import TASK_RUN_JOB, enqueue, make_celery
from kernel.settings import get_settings

log = logging.getLogger("drop.worker")
settings = get_settings()
celery = make_celery(settings)
_stop = threading.Event()


def _shutdown_marker(main_pid: int) -> Path:
    return Path(tempfile.gettempdir()) / f"drop-worker-{main_pid}.stopping"


def _shutdown_check():
    """In the pool child: true once the worker's main process is shutting down (warm) or has died."""
    parent = os.getppid()
    marker = _shutdown_marker(parent)
    return lambda: os.getppid() != parent or marker.exists()


@celery.task(name=TASK_RUN_JOB)
def run_job(job_id: str) -> str:
    from .runner import run_job as run

    engine = make_engine(settings.sqlalchemy_url)  # in the child process: never share connections across fork
    try:
        return run(settings, make_sessionmaker(engine), job_id, _shutdown_check())
    finally:
        engine.dispose()


def _reaper_loop(slots: int) -> None:
    from celery.worker import state

    from kernel.models import utcnow

    from .reaper import reap

    engine = make_engine(settings.sqlalchemy_url)
    sessions = make_sessionmaker(engine)
    first, idle_since = True, None
    try:
        while first or not _stop.wait(settings.reap_every_s):  # a pass at start-up picks up jobs a stopped worker left
            first = False
            # reserved_requests holds the jobs this worker has taken (running or waiting for a pool process).
            idle_since = (idle_since or utcnow()) if len(state.reserved_requests) < slots else None
            try:
                sent = reap(sessions, settings, lambda job_id, rt: enqueue(celery, settings, job_id, rt), idle_since)
                if sent:
                    log.warning("reaper re-sent jobs %s", ", ".join(sent))
            except Exception:
                log.exception("reaper pass failed")
    finally:
        engine.dispose()


@setup_logging.connect
def _keep_our_logging(**_) -> None:
    """`drop worker` set up logging (kernel/logs.py) before Celery started; a receiver here stops Celery replacing
    it."""


@worker_process_init.connect
def _yield_to_the_api(**_) -> None:
    """A pool process trains for minutes to hours at full CPU; on a machine shared with the API, requests waited
    behind it (bench/results/service_load.md). Niced, it gets the CPU whenever nothing more urgent wants it."""
    if settings.worker_nice:
        os.nice(settings.worker_nice)


@worker_ready.connect
def _start_reaper(sender, **_) -> None:
    _shutdown_marker(os.getpid()).unlink(missing_ok=True)  # left by a crashed worker that had our pid
    threading.Thread(target=_reaper_loop, args=(sender.controller.concurrency,), daemon=True, name="reaper").start()


@worker_shutting_down.connect
def _ask_jobs_to_stop(**_) -> None:
    """Warm shutdown (SIGTERM): running jobs checkpoint and go back to the queue instead of holding the exit."""
    _stop.set()
    _shutdown_marker(os.getpid()).touch()


@worker_shutdown.connect
def _cleanup(**_) -> None:
    _stop.set()
    _shutdown_marker(os.getpid()).unlink(missing_ok=True)
