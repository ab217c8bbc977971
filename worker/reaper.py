"""Find jobs whose worker died (stale heartbeat) and re-queue or fail them; re-send queued jobs whose message never
reached the broker or was lost there (Redis restarted without persistence keeps no messages).

Every change is a conditional UPDATE on the row as it was seen (kernel.job_state.transition), so several reapers (one
per worker) never collide: of several reapers, one takes each re-send. A job sent twice still runs once, because
claiming it is conditional too.
"""
from __future__ import annotations

import logging
from datetime import datetime, timedelta

from sqlalchemy import exists, select
from sqlalchemy.orm import Session, sessionmaker

from kernel.job_state import ATTEMPT, JobStatus, mark_sent, status_in, transition
from kernel.models import Job, JobCheckpoint, utcnow
from kernel.queue import Enqueue
from kernel.settings import Settings

log = logging.getLogger("drop.reaper")


def reap(sessions: sessionmaker[Session], settings: Settings, enqueue: Enqueue,
         idle_since: datetime | None = None) -> list[str]:
    """One pass; returns the ids of jobs it re-queued or re-sent.

    `idle_since`: since when this worker has had a free slot. A worker with a free slot takes any message in its
    queue, so a job still queued a while later whose message was sent before then has lost its message."""
    now = utcnow()
    _expire_dead(sessions, settings, now)
    # Never sent (broker down at creation: give the API 10 s to send it itself) or handed back by a worker.
    due = Job.enqueued_at.is_(None) & ((Job.created_at < now - timedelta(seconds=10)) | (Job.attempts > 0)
                                       | Job.started_at.is_not(None))
    if idle_since is not None and idle_since <= now - timedelta(seconds=settings.redeliver_after_s):
        due = due | (Job.enqueued_at < idle_since)
    with sessions() as s:
        rows = s.execute(select(Job.id, Job.max_runtime_s).where(Job.status == JobStatus.QUEUED, due)).all()
    return [row.id for row in rows if _resend(sessions, enqueue, row.id, row.max_runtime_s, due)]


def _expire_dead(sessions: sessionmaker[Session], settings: Settings, now: datetime) -> None:
    """Re-queue (unsent, for the caller to send) or end the jobs whose worker stopped heartbeating."""
    stale = now - timedelta(seconds=settings.stale_after_s)
    with sessions() as s:
        checkpointed = exists().where(JobCheckpoint.job_id == Job.id).label("checkpointed")
        dead = s.execute(select(Job.id, Job.status, Job.attempts, Job.max_attempts, checkpointed)
                         .where(status_in(ATTEMPT), Job.heartbeat_at < stale)).all()
    for row in dead:
        if row.status == JobStatus.CANCELLING:
            to, values, message = JobStatus.CANCELLED, {"finished_at": now}, "cancelled (its worker stopped responding)"
        elif row.attempts >= row.max_attempts:
            reason = (f"attempts exhausted: the worker stopped responding on all {row.attempts} attempts "
                      f"(max_attempts={row.max_attempts})")
            to, message = JobStatus.FAILED, f"failed: {reason}"
            values = {"finished_at": now, "error_code": "worker_lost", "error_message": reason}
        else:
            to, values = JobStatus.QUEUED, {"worker": None, "enqueued_at": None}
            then = "will resume from checkpoint" if row.checkpointed else "will start over (no checkpoint was written)"
            message = f"re-queued: the worker of attempt {row.attempts} stopped responding; {then}"
        # Only the row as it was seen: the same status, still the same attempt, and still silent (a heartbeat
        # between the query and this UPDATE means its worker is alive).
        with sessions.begin() as s:
            transition(s, row.id, to, source=JobStatus(row.status), attempt=row.attempts,
                       where=Job.heartbeat_at < stale, values=values, message=message)


def _resend(sessions: sessionmaker[Session], enqueue: Enqueue, job_id: str, runtime: int, due) -> bool:
    """Take the re-send (the UPDATE repeats the query's condition, so one reaper wins), then send; on failure mark the
    job unsent, for the next pass."""
    with sessions.begin() as s:
        if not mark_sent(s, job_id, utcnow(), where=due):
            return False
    try:
        enqueue(job_id, runtime)
    except Exception:
        log.exception("could not enqueue %s", job_id)
        with sessions.begin() as s:
            mark_sent(s, job_id, None)
        return False
    return True
