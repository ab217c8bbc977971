"""Run one job: claim it, train with the database callback while heartbeating, record how it ended.

The claim is a single conditional UPDATE (queued -> running, on the attempt count it read), which is atomic on
PostgreSQL and SQLite alike: of two deliveries of the same message, exactly one wins, and the loser does nothing.
Every status change goes through kernel.job_state.transition, fenced by this worker's attempt.
"""
from __future__ import annotations

import logging
import os
import socket
import threading
import time
import traceback
from datetime import datetime
from pathlib import Path
from typing import Callable

from sqlalchemy import func, select, update
from sqlalchemy.exc import DBAPIError, IntegrityError, InterfaceError
from sqlalchemy.orm import Session, sessionmaker

from kernel.exc_chain import causes
from kernel.job_state import JobStatus, mark_sent, still_attempt, transition
from kernel.logs import bound
from kernel.models import Dataset, Job, JobEvent, utcnow
from kernel.settings import Settings
from kernel.storage import from_stored, job_dir, model_cache_dir, remove_tree
from kernel.storage_errors import storage_failure

from .callback import DbCallback
from .failures import unexpected_failure

log = logging.getLogger("drop.worker")
FINISH_RETRY_S = (1.0, 2.0, 4.0, 8.0)


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def claim(sessions: sessionmaker[Session], job_id: str, name: str) -> int | None:
    """The attempt number if this worker now owns the job, else None."""
    with sessions() as s:
        seen = s.execute(select(Job.attempts, Job.max_attempts, Job.created_at).where(Job.id == job_id)).one_or_none()
    if seen is None or seen.attempts >= seen.max_attempts:
        return None
    attempt, now = seen.attempts + 1, utcnow()
    with sessions.begin() as s:  # the UPDATE first: a SQLite transaction that read first may not then write
        won = transition(s, job_id, JobStatus.RUNNING, where=Job.attempts == seen.attempts,
                         values={"attempts": attempt, "worker": name, "heartbeat_at": now, "started_at": now,
                                 # the first claim ends the job's wait in the queue
                                 "queue_wait_s": func.coalesce(Job.queue_wait_s, _seconds(seen.created_at, now))},
                         message=f"running (attempt {attempt} on {name})", data={"attempt": attempt, "worker": name})
    return attempt if won else None


def _seconds(start: datetime | None, end: datetime) -> float:
    return max(0.0, (end - start).total_seconds()) if start is not None else 0.0


def _ran(started_at: datetime | None, now: datetime):
    """The job's run_s plus this attempt's seconds, as an SQL expression."""
    return func.coalesce(Job.run_s, 0.0) + _seconds(started_at, now)


def finish(sessions: sessionmaker[Session], job_id: str, attempt: int, status: JobStatus, message: str, *,
           error: tuple[str, str] | None = None, trace: str | None = None) -> bool:
    """Record the end of this attempt, unless the job is no longer ours.

    A lost database connection is tried again four times over 15 s of pauses (the heartbeat keeps the job this
    attempt's meanwhile): failing here would leave a finished run to the reaper, and cost it another attempt, or its
    last."""
    now = utcnow()
    values = {"finished_at": now, "heartbeat_at": now}
    if error:
        values.update(error_code=error[0], error_message=error[1])
    delays, retry = iter(FINISH_RETRY_S), False
    while True:
        try:
            with sessions.begin() as s:
                started_at = s.scalar(select(Job.started_at).where(Job.id == job_id))
                if not transition(s, job_id, status, attempt=attempt, values={**values, "run_s": _ran(started_at, now)},
                                  message=message,
                                  data={"error": {"code": error[0], "message": error[1]}} if error else None):
                    # A retry whose earlier commit went through, its answer lost, finds its own write (after the
                    # UPDATE, which waited for that commit if it was still in flight).
                    return retry and _recorded(s, job_id, attempt, status, now)
                if trace:
                    s.add(JobEvent(job_id=job_id, type="traceback", message=trace[-20000:], data=None))
            return True
        except DBAPIError as exc:
            delay = next(delays, None)
            if delay is None or not _connection_lost(exc):
                raise
            log.warning("job %s: recording %s failed on the database connection; again in %s s", job_id, status.value,
                        delay, exc_info=True)
            time.sleep(delay)
            retry = True


def _connection_lost(exc: BaseException) -> bool:
    """The database connection failed (the server went, restarted or ended the session), not a statement: a
    statement's own error (a timeout, a lock, a full disk) fails the job and records why."""
    return any(isinstance(e, InterfaceError) or (isinstance(e, DBAPIError) and e.connection_invalidated)
               for e in causes(exc))


def _recorded(s: Session, job_id: str, attempt: int, status: JobStatus, finished_at: datetime) -> bool:
    """Whether an earlier try of this record committed though its answer was lost: the row holds its very write."""
    return s.scalar(select(Job.id).where(Job.id == job_id, Job.attempts == attempt, Job.status == status.value,
                                         Job.finished_at == finished_at)) is not None


class Heartbeat(threading.Thread):
    """Touches heartbeat_at every few seconds so the reaper can tell a live job from a dead worker."""

    def __init__(self, sessions: sessionmaker[Session], job_id: str, attempt: int, every_s: float):
        super().__init__(daemon=True, name=f"heartbeat-{job_id}")
        self.sessions, self.job_id, self.attempt, self.every_s = sessions, job_id, attempt, every_s
        self.stopped = threading.Event()

    def run(self) -> None:
        while not self.stopped.wait(self.every_s):
            try:
                with self.sessions.begin() as s:
                    s.execute(update(Job).where(Job.id == self.job_id, still_attempt(self.attempt))
                              .values(heartbeat_at=utcnow()))
            except Exception:  # a database blip must not kill the job; the next beat retries
                log.exception("heartbeat for %s failed", self.job_id)

    def stop(self) -> None:
        """Returns once a beat in flight has ended, so the thread does not outlive its job (bounded: a hung database
        must not hold the worker)."""
        self.stopped.set()
        self.join(timeout=self.every_s)


def _fail(sessions: sessionmaker[Session], settings: Settings, job_id: str, attempt: int, code: str, message: str,
          trace: str) -> str:
    """'failed', or 'lost' if the job was no longer this attempt's: a job deleted under a worker that had lost it
    fails that worker's stop checkpoint too, and that is not the job's failure."""
    if finish(sessions, job_id, attempt, JobStatus.FAILED, f"failed: {message}", error=(code, message), trace=trace):
        return "failed"
    return _lost(sessions, settings, job_id, attempt)


def _lost(sessions: sessionmaker[Session], settings: Settings, job_id: str, attempt: int) -> str:
    """The end of an attempt whose job was taken from it: nothing is recorded, as the job is another's or gone."""
    log.warning("job %s: this worker lost it (attempt %s); stopped without recording", job_id, attempt)
    with sessions() as s:
        deleted = s.get(Job, job_id) is None
    if deleted:  # a reaper had given it up and its owner deleted it: the stop's checkpoint must not outlive it
        remove_tree(job_dir(settings, job_id))
    return "lost"


def requeue(sessions: sessionmaker[Session], job_id: str, attempt: int, message: str) -> bool:
    """Give the job back (its worker is shutting down); the attempt does not count against max_attempts."""
    with sessions.begin() as s:
        started_at = s.scalar(select(Job.started_at).where(Job.id == job_id))
        return transition(s, job_id, JobStatus.QUEUED, attempt=attempt, message=message,
                          values={"worker": None, "enqueued_at": None, "attempts": Job.attempts - 1,
                                  "run_s": _ran(started_at, utcnow())})


def _add_onnx(sessions: sessionmaker[Session], job_id: str, attempt: int, result, obs_dim: int) -> None:
    """An ONNX copy beside each exported policy (last and best). Best effort: a policy that cannot be expressed in ONNX
    still leaves TorchScript and state_dict. The warning is fenced like every write of the attempt: a job deleted
    meanwhile has no row for it to point to."""
    from drop_engine.export import export_onnx
    from drop_engine.policy_files import FILE_NAMES

    for which, files in result.policy.items():
        try:
            torchscript = Path(files["torchscript"])
            export_onnx(torchscript, obs_dim, torchscript.with_name(FILE_NAMES["onnx"]))
        except Exception as exc:
            log.exception("ONNX export of %s's %s policy failed", job_id, which)
            try:
                with sessions.begin() as s:
                    if s.scalar(select(Job.id).where(Job.id == job_id, still_attempt(attempt)).with_for_update()):
                        s.add(JobEvent(job_id=job_id, type="warning", message=f"ONNX export of the {which} policy "
                                       f"failed: {type(exc).__name__}: {exc}"))
            except IntegrityError:  # SQLite locks no row: the job was deleted between the check and the insert
                log.warning("job %s was deleted before its ONNX warning was written", job_id)


def release_unclaimed(sessions: sessionmaker[Session], job_id: str) -> None:
    """A shutting-down worker got the message: leave the job queued and mark it unsent, for a reaper to send again."""
    with sessions.begin() as s:
        mark_sent(s, job_id, None)


def run_job(settings: Settings, sessions: sessionmaker[Session], job_id: str,
            shutting_down: Callable[[], bool] = lambda: False) -> str:
    """Run the job if we can claim it; returns the final status, 'requeued', 'skipped', or 'interrupted' (the
    database connection failed: the job is left to the reaper).

    `shutting_down` is polled between steps: when it turns true the run stops with a checkpoint and the job goes back
    to the queue, to resume from that checkpoint on the next worker."""
    started = time.monotonic()  # the task's soft time limit counts from here, engine imports included
    if shutting_down():
        release_unclaimed(sessions, job_id)
        return "skipped"
    name = worker_name()
    attempt = claim(sessions, job_id, name)  # before the slow engine imports, so the status turns at once
    if attempt is None:
        log.info("job %s not claimable (already taken, finished or cancelled)", job_id)
        return "skipped"
    with sessions() as s:
        job = s.get(Job, job_id)
        dataset = s.get(Dataset, job.dataset_id) if job.dataset_id else None
        config_data = dict(job.config)
    if settings.worker_threads:
        config_data["threads"] = settings.worker_threads
    callback = DbCallback(sessions, job_id, attempt, settings, shutting_down)
    heartbeat = Heartbeat(sessions, job_id, attempt, settings.heartbeat_s)
    heartbeat.start()
    with bound(job_id=job_id, attempt=attempt, worker=name):  # on every log line of this attempt
        log.info("claimed job %s, attempt %s", job_id, attempt)
        try:
            status = _train_and_record(sessions, job, dataset, config_data, settings, attempt, callback, started)
        except Exception as exc:
            if not _connection_lost(exc):
                raise
            # Not recorded, as the database is what failed: with the heartbeat stopped, a reaper re-queues the job
            # (the attempt counts) and the next attempt resumes from the newest checkpoint, or fails it as
            # worker_lost once its attempts are used up.
            log.warning("job %s: attempt %s lost its database connection; left to the reaper", job_id, attempt,
                        exc_info=True)
            status = "interrupted"
        finally:
            heartbeat.stop()
        log.info("job %s attempt %s ended: %s", job_id, attempt, status)
        return status


def _train_and_record(sessions: sessionmaker[Session], job: Job, dataset: Dataset | None, config_data: dict,
                      settings: Settings, attempt: int, callback: DbCallback, started: float) -> str:
    """Train, then record how it ended; every write is fenced by `attempt`."""
    from celery.exceptions import SoftTimeLimitExceeded

    from drop_engine.config import TrainConfig
    from drop_engine.divergence import TrainingDiverged
    from drop_engine.errors import DatasetError
    from drop_engine.trainer import train

    job_id = job.id
    try:
        data_file = from_stored(settings, dataset.path) if dataset is not None else None
        if data_file is None or not data_file.is_file():
            raise DatasetError("file: the job's dataset was deleted")
        result = train(data_file, TrainConfig.model_validate(config_data), job_dir(settings, job_id), callback,
                       model_cache_dir(settings))
    except DatasetError as exc:
        return _fail(sessions, settings, job_id, attempt, "invalid_dataset", str(exc), traceback.format_exc())
    except TrainingDiverged as exc:
        return _fail(sessions, settings, job_id, attempt, "training_diverged", str(exc), traceback.format_exc())
    except Exception as exc:
        # The soft limit is raised from a signal handler wherever the job happens to be, and a library may wrap
        # it in its own error type (psycopg, interrupted mid-query): past the deadline, any failure is the timeout.
        if (any(isinstance(e, SoftTimeLimitExceeded) for e in causes(exc))
                or time.monotonic() - started >= job.max_runtime_s):
            return _fail(sessions, settings, job_id, attempt, "timeout",
                         f"the attempt ran past max_runtime_s={job.max_runtime_s}", traceback.format_exc())
        if _connection_lost(exc):  # a blip of the database, not the job's failure: run_job leaves it to the reaper
            raise
        log.exception("job %s failed", job_id)
        # A full or read-only disk fails the job rather than retrying it: another attempt would meet the same disk.
        code, message = storage_failure(exc, "the run's checkpoint or policy") or unexpected_failure(exc)
        return _fail(sessions, settings, job_id, attempt, code, message, traceback.format_exc())
    if result.status == "completed":
        _add_onnx(sessions, job_id, attempt, result, dataset.obs_dim)
        if finish(sessions, job_id, attempt, JobStatus.SUCCEEDED, "succeeded"):
            return "succeeded"
        return _lost(sessions, settings, job_id, attempt)
    # A run stopped while fitting its dynamics model has written no checkpoint yet: say so, not that it wrote one.
    checkpointed = result.checkpoint is not None
    if callback.stop_reason == "cancelled" and finish(
            sessions, job_id, attempt, JobStatus.CANCELLED, "cancelled at a step boundary; final checkpoint written"
            if checkpointed else "cancelled before its first checkpoint; nothing to resume was written"):
        return "cancelled"
    if callback.stop_reason == "shutdown":
        # Not re-sent from here: this worker would take the message back while it shuts down. The reaper of the
        # next worker to start (or of any live one) sends it, because enqueued_at is cleared.
        then = ("will resume from checkpoint" if checkpointed
                else "will start over (stopped before its first checkpoint)")
        if requeue(sessions, job_id, attempt, f"re-queued: its worker is shutting down; {then}"):
            return "requeued"
        if finish(sessions, job_id, attempt, JobStatus.CANCELLED, "cancelled while its worker was shutting down"):
            return "cancelled"
    return _lost(sessions, settings, job_id, attempt)
