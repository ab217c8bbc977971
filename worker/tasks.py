"""Celery entry points: the `drop.run_job` task and the reaper thread of each worker's main process."""
from __future__ import annotations

import logging
import threading

from celery.signals import worker_ready, worker_shutdown

from app.db import make_engine, make_sessionmaker
from app.settings import get_settings

from .celery_app import TASK_RUN_JOB, enqueue, make_celery

log = logging.getLogger("drop.worker")
settings = get_settings()
celery = make_celery(settings)
_stop = threading.Event()


@celery.task(name=TASK_RUN_JOB)
def run_job(job_id: str) -> str:
    from .runner import run_job as run

    engine = make_engine(settings.sqlalchemy_url)  # in the child process: never share connections across fork
    try:
        return run(settings, make_sessionmaker(engine), job_id)
    finally:
        engine.dispose()


def _reaper_loop() -> None:
    from .reaper import reap

    engine = make_engine(settings.sqlalchemy_url)
    sessions = make_sessionmaker(engine)
    while not _stop.wait(settings.reap_every_s):
        try:
            sent = reap(sessions, settings, lambda job_id, rt: enqueue(celery, settings, job_id, rt))
            if sent:
                log.warning("reaper re-sent jobs %s", ", ".join(sent))
        except Exception:
            log.exception("reaper pass failed")


@worker_ready.connect
def _start_reaper(**_) -> None:
    threading.Thread(target=_reaper_loop, daemon=True, name="reaper").start()


@worker_shutdown.connect
def _stop_reaper(**_) -> None:
    _stop.set()
