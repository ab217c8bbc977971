"""Find jobs whose worker died (stale heartbeat) and re-queue or fail them; re-send jobs never enqueued.

Every change is a conditional UPDATE on the row as it was seen, so several reapers (one per worker) never collide.
"""
from __future__ import annotations

import logging
from datetime import timedelta
from typing import Callable

from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from app.models import Job, JobEvent, utcnow
from app.settings import Settings

log = logging.getLogger("drop.reaper")
Enqueue = Callable[[str, int], None]


def reap(sessions: sessionmaker[Session], settings: Settings, enqueue: Enqueue) -> list[str]:
    """One pass; returns the ids of jobs it re-queued or re-sent."""
    now = utcnow()
    stale = now - timedelta(seconds=settings.stale_after_s)
    resend: list[tuple[str, int]] = []
    with sessions() as s:
        dead = s.execute(select(Job.id, Job.status, Job.attempts, Job.max_attempts, Job.heartbeat_at, Job.max_runtime_s)
                         .where(Job.status.in_(("running", "cancelling")), Job.heartbeat_at < stale)).all()
        # Never sent (broker down at creation: give the API 10 s to send it itself) or handed back by a worker.
        unsent = s.execute(select(Job.id, Job.max_runtime_s).where(
            Job.status == "queued", Job.enqueued_at.is_(None),
            (Job.created_at < now - timedelta(seconds=10)) | (Job.attempts > 0) | Job.started_at.is_not(None))).all()
    for row in dead:
        seen = (Job.id == row.id) & (Job.attempts == row.attempts) & (Job.status == row.status)
        if row.status == "cancelling":
            values, message = {"status": "cancelled", "finished_at": now}, "cancelled (its worker stopped responding)"
        elif row.attempts >= row.max_attempts:
            values = {"status": "failed", "finished_at": now, "error_code": "worker_lost",
                      "error_message": f"the worker stopped responding on all {row.attempts} attempts"}
            message = "failed: worker lost on the last attempt"
        else:
            values = {"status": "queued", "worker": None, "enqueued_at": None}
            message = f"re-queued: the worker of attempt {row.attempts} stopped responding; will resume from checkpoint"
        with sessions.begin() as s:
            if s.execute(update(Job).where(seen).values(**values)).rowcount:
                s.add(JobEvent(job_id=row.id, type="status", message=message, data={"status": values["status"]}))
                if values["status"] == "queued":
                    resend.append((row.id, row.max_runtime_s))
    resend.extend((r.id, r.max_runtime_s) for r in unsent)
    sent = []
    for job_id, runtime in resend:
        try:
            enqueue(job_id, runtime)
        except Exception:
            log.exception("could not enqueue %s", job_id)
            continue
        with sessions.begin() as s:
            s.execute(update(Job).where(Job.id == job_id).values(enqueued_at=utcnow()))
        sent.append(job_id)
    return sent
