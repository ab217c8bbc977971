"""The hot reads (a job, the job list, a job's events) as plain functions on a session factory.

A route runs one of these in the threadpool in a single hop, with a session of its own held only for the query (from
`app.state.reader`: autocommit, so a read is one round trip, not BEGIN, SELECT and ROLLBACK), and sends the dicts as
they are: the serializers already produce the documented shapes, so validating them again against
the response model would only spend the time twice.
"""
from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session, defer, sessionmaker

from . import serialize
from .deps import owned_job
from kernel.job_state import JobStatus
from kernel.models import Job, JobEvent
from .problems import Problem


def job(sessions: sessionmaker[Session], owner: str, job_id: str) -> dict:
    with sessions() as s:
        return serialize.job(owned_job(s, owner, job_id))


def jobs_page(sessions: sessionmaker[Session], owner: str, status: str | None, after: str | None, limit: int) -> dict:
    q = select(Job).where(Job.owner_id == owner).options(defer(Job.result))
    if status is not None:
        if status not in set(JobStatus):
            raise Problem(422, "validation_error", f"status: must be one of {', '.join(JobStatus)}",
                          errors=[{"field": "status", "message": "unknown status"}])
        q = q.where(Job.status == status)
    if after:
        q = q.where(Job.id < after)
    with sessions() as s:
        return serialize.fetch_page(s, q.order_by(Job.id.desc()), serialize.job, limit)


def events_page(sessions: sessionmaker[Session], owner: str, job_id: str, after: int, limit: int) -> dict:
    with sessions() as s:
        owned_job(s, owner, job_id)
        q = select(JobEvent).where(JobEvent.job_id == job_id, JobEvent.id > after).order_by(JobEvent.id)
        return serialize.fetch_page(s, q, serialize.event, limit)
