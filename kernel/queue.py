"""The Celery app, configured for hour-long CPU jobs where the database, not the broker, is the truth.

- prefetch 1 and one task per child process: a worker never hoards jobs, and each job gets a fresh process.
- acks_late with reject_on_worker_lost: a message survives a worker crash; a redelivered copy is harmless because
  the task claims the job row with a conditional UPDATE (queued -> running) and does nothing if that fails.
- time limits are set per message from the job's max_runtime.
- a lost broker connection leaves running jobs running: they report to the database, and the reaper sends again
  queued jobs whose message the broker lost.
"""
from __future__ import annotations

from typing import Callable

from celery import Celery

from .settings import Settings

TASK_RUN_JOB = "drop.run_job"
# Sends a job (id, max runtime in seconds) to the workers: the API after creating it, the reaper re-sending it. Both
# take it as a parameter, so tests can record what was sent.
Enqueue = Callable[[str, int], None]


def make_celery(settings: Settings) -> Celery:
    app = Celery("drop", broker=settings.celery_broker_url)
    conf = {
        "task_default_queue": settings.queue,
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "worker_prefetch_multiplier": 1,
        "worker_max_tasks_per_child": 1,
        "worker_concurrency": settings.worker_concurrency,
        "task_ignore_result": True,
        "task_serializer": "json",
        "accept_content": ["json"],
        "broker_connection_retry_on_startup": True,
        "worker_cancel_long_running_tasks_on_connection_loss": False,
        "worker_hijack_root_logger": False,
        "worker_send_task_events": False,
        "broker_transport_options": {"visibility_timeout": 7 * 24 * 3600},
    }
    if settings.is_filesystem_broker:
        folder = str((settings.data_dir / "broker" / "queue").resolve())
        conf["broker_transport_options"] = {
            "data_folder_in": folder, "data_folder_out": folder,
            "processed_folder": str((settings.data_dir / "broker" / "processed").resolve()),
            "control_folder": str((settings.data_dir / "broker" / "control").resolve()),
            "store_processed": False,
        }
    app.conf.update(conf)
    return app


def enqueue(celery: Celery, settings: Settings, job_id: str, max_runtime_s: int) -> None:
    """Deliver "run job N"; the soft limit lets the task record a timeout, the hard limit kills it 60 s later."""
    celery.send_task(TASK_RUN_JOB, args=[job_id], queue=settings.queue,
                     soft_time_limit=max_runtime_s, time_limit=max_runtime_s + 60)
