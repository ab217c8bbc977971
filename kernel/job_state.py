"""The job state machine: the statuses, the moves allowed between them, and the one function that makes a move.

Several processes write a job's row at once: the API (create, cancel), the worker running it (claim, finish,
requeue, release) and every worker's reaper (expire, resend). Each move is one conditional UPDATE whose WHERE clause
holds what its writer assumes (the statuses the table allows to become the new one and, for a worker, that the row is
still its attempt), committed with the event that tells the job's owner. Of two writers racing, one moves the row and
the other finds it moved and writes nothing, on PostgreSQL and SQLite alike.
"""
from __future__ import annotations

from datetime import datetime
from enum import Enum
from typing import Any, Iterable, Mapping

from sqlalchemy import ColumnElement, update
from sqlalchemy.orm import Session

from .models import Job, JobEvent


class JobStatus(str, Enum):
    QUEUED = "queued"
    RUNNING = "running"
    CANCELLING = "cancelling"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"

    def __str__(self) -> str:  # the value in messages, as StrEnum (Python 3.11) would give
        return self.value


QUEUED, RUNNING, CANCELLING = JobStatus.QUEUED, JobStatus.RUNNING, JobStatus.CANCELLING
SUCCEEDED, FAILED, CANCELLED = JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELLED
ACTIVE = frozenset({QUEUED, RUNNING, CANCELLING})  # unfinished: they count toward a quota and hold their dataset
ATTEMPT = frozenset({RUNNING, CANCELLING})  # an attempt holds the job: its worker's writes are fenced to these
FINAL = frozenset({SUCCEEDED, FAILED, CANCELLED})

# Each status and the statuses it may become; who makes each move is in docs/ARCHITECTURE.md. A job is created queued.
TRANSITIONS: Mapping[JobStatus, frozenset[JobStatus]] = {
    QUEUED: frozenset({
        QUEUED,  # its message was sent, or must be sent again (enqueued_at): API create, reaper resend, worker release
        RUNNING,  # worker claim
        CANCELLED,  # API cancel
    }),
    RUNNING: frozenset({
        QUEUED,  # worker requeue (shutting down); reaper expire (heartbeat stale, attempts left)
        CANCELLING,  # API cancel
        SUCCEEDED,  # worker finish
        FAILED,  # worker finish; reaper expire (heartbeat stale, attempts exhausted)
    }),
    CANCELLING: frozenset({
        SUCCEEDED,  # worker finish: the run ended before it saw the request
        FAILED,  # worker finish
        CANCELLED,  # worker finish; reaper expire (heartbeat stale)
    }),
    SUCCEEDED: frozenset(),
    FAILED: frozenset(),
    CANCELLED: frozenset(),
}


class ForbiddenTransition(ValueError):
    """A writer named a move the table does not allow: a bug in the writer, not a race."""


def sources(to: JobStatus) -> frozenset[JobStatus]:
    """The statuses that may become `to`."""
    return frozenset(s for s, targets in TRANSITIONS.items() if to in targets)


def status_in(statuses: Iterable[JobStatus]) -> ColumnElement[bool]:
    """The job's status is one of `statuses`, as SQL."""
    return Job.status.in_(sorted(s.value for s in statuses))


def still_attempt(attempt: int) -> ColumnElement[bool]:
    """The fence of a worker's writes: the row is still attempt `attempt`, running or being cancelled. A worker whose
    job was taken from it (re-queued by a reaper, then claimed again) no longer matches, and writes nothing."""
    return (Job.attempts == attempt) & status_in(ATTEMPT)


def create(s: Session, job: Job) -> None:
    """Add the new job, queued, with its first event, in the caller's transaction: the only move that is an INSERT."""
    job.status = QUEUED.value
    s.add(job)
    s.add(JobEvent(job_id=job.id, type="status", message="queued", data={"status": QUEUED.value}))


def transition(s: Session, job_id: str, to: JobStatus, *, source: JobStatus | None = None, attempt: int | None = None,
               where: ColumnElement[bool] | None = None, values: Mapping[str, Any] | None = None,
               message: str | None = None, data: Mapping[str, Any] | None = None) -> bool:
    """Move job `job_id` to `to`, setting `values`, and record a status event saying `message` (none when None) with
    `data`, both in the caller's transaction; or change nothing.

    The row moves only from a status the table allows to become `to` (from `source` alone, when given), while it is
    still attempt `attempt` (when given) and meets `where`. Returns whether it moved: False when the row was in a
    status it may not move from, or another writer moved it first. A `source` the table forbids raises."""
    if source is not None and to not in TRANSITIONS[source]:
        raise ForbiddenTransition(f"a job cannot go from {source} to {to}")
    fence = (Job.id == job_id) & status_in({source} if source is not None else sources(to))
    if attempt is not None:
        fence &= still_attempt(attempt)
    if where is not None:
        fence &= where
    if not s.execute(update(Job).where(fence).values(status=to.value, **(values or {}))).rowcount:
        return False
    if message is not None:
        s.add(JobEvent(job_id=job_id, type="status", message=message, data={"status": to.value, **(data or {})}))
    return True


def mark_sent(s: Session, job_id: str, sent_at: datetime | None, where: ColumnElement[bool] | None = None) -> bool:
    """Record that the queued job's message went to the broker at `sent_at`, or, with None, that it must be sent
    (again): a reaper sends every queued job whose `enqueued_at` is null."""
    return transition(s, job_id, QUEUED, source=QUEUED, where=where, values={"enqueued_at": sent_at})
