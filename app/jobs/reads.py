"""What the job routes read: a job by its owner (404 otherwise), the job list, a job's events and its outputs.

The hot reads (a job, the job list, a job's events) are plain functions on a session factory. A route runs one in the
threadpool in a single hop, with a session of its own held only for the query (from `app.state.reader`: autocommit,
so a read is one round trip, not BEGIN, SELECT and ROLLBACK), and sends the dicts as they are: the serializers
already produce the documented shapes, so validating them again against the response model would only spend the
time twice.
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal

from sqlalchemy import select
from sqlalchemy.orm import Session, defer, sessionmaker

from drop_engine.scores import Which
from kernel.ids import is_id
from kernel.job_state import JobStatus
from kernel.models import Job, JobCheckpoint, JobEvaluation, JobEvent, JobMetric
from kernel.settings import Settings
from kernel.storage import job_dir

from ..core.pages import fetch_page, page
from ..core.problems import Problem
from . import schemas

PolicyFormat = Literal["torchscript", "state_dict", "onnx", "metadata"]
POLICY_FILES = {"torchscript": ("policy.pt", "application/octet-stream"),
                "state_dict": ("policy_state_dict.pt", "application/octet-stream"),
                "onnx": ("policy.onnx", "application/octet-stream"),
                "metadata": ("metadata.json", "application/json")}


def owned_job(s: Session, owner_id: str, job_id: str) -> Job:
    """The owner's job or 404."""
    # The API never shows a job's `result` (the engine's full report), so it is not read.
    q = select(Job).where(Job.id == job_id, Job.owner_id == owner_id).options(defer(Job.result))
    row = s.scalar(q) if is_id(job_id, "job") else None
    if row is None:
        raise Problem(404, "not_found", f"job {job_id} not found")
    return row


def job(sessions: sessionmaker[Session], owner: str, job_id: str) -> dict:
    with sessions() as s:
        return schemas.job(owned_job(s, owner, job_id))


def jobs_page(sessions: sessionmaker[Session], owner: str, status: JobStatus | None, after: str | None,
              limit: int) -> dict:
    q = select(Job).where(Job.owner_id == owner).options(defer(Job.result))
    if status is not None:
        q = q.where(Job.status == status.value)
    if after:
        q = q.where(Job.id < after)
    with sessions() as s:
        return fetch_page(s, q.order_by(Job.id.desc()), schemas.job, limit)


def events_page(sessions: sessionmaker[Session], owner: str, job_id: str, after: int, limit: int) -> dict:
    with sessions() as s:
        owned_job(s, owner, job_id)
        q = select(JobEvent).where(JobEvent.job_id == job_id, JobEvent.id > after).order_by(JobEvent.id)
        return fetch_page(s, q, schemas.event, limit)


def events_after(sessions: sessionmaker[Session], job_id: str, after: int, limit: int) -> tuple[list[dict], str]:
    """(events after `after`, the job's status), for the event stream. The status is read first: a final status
    commits together with its events, so when it is final here they are all in the rows read next, and the stream
    cannot end short of them."""
    with sessions() as s:
        status = s.scalar(select(Job.status).where(Job.id == job_id))
        rows = s.scalars(select(JobEvent).where(JobEvent.job_id == job_id, JobEvent.id > after)
                         .order_by(JobEvent.id).limit(limit))
        return [schemas.event(r) for r in rows], status


def metrics_page(s: Session, owner: str, job_id: str, name: str | None, after: int, limit: int) -> dict:
    owned_job(s, owner, job_id)
    q = select(JobMetric).where(JobMetric.job_id == job_id, JobMetric.id > after)
    if name:
        q = q.where(JobMetric.name == name)
    return fetch_page(s, q.order_by(JobMetric.id), schemas.metric, limit)


def evaluations(s: Session, owner: str, job_id: str) -> list[JobEvaluation]:
    owned_job(s, owner, job_id)
    return list(s.scalars(select(JobEvaluation).where(JobEvaluation.job_id == job_id).order_by(JobEvaluation.id)))


def evaluations_page(s: Session, owner: str, job_id: str) -> dict:
    return page([schemas.evaluation(r) for r in evaluations(s, owner, job_id)], False)


def checkpoints_page(s: Session, owner: str, job_id: str) -> dict:
    """The checkpoints still on disk (the trainer prunes older ones)."""
    owned_job(s, owner, job_id)
    rows = s.scalars(select(JobCheckpoint).where(JobCheckpoint.job_id == job_id).order_by(JobCheckpoint.id))
    return page([schemas.checkpoint(r) for r in rows if Path(r.path).is_file()], False)


def policy_file(s: Session, owner: str, job_id: str, which: Which, fmt: PolicyFormat,
                settings: Settings) -> tuple[Path, str]:
    """(path, media type) of the job's `which` policy in format `fmt`: 409 until the job has succeeded, 404 if that
    file is missing."""
    row = owned_job(s, owner, job_id)
    if row.status != JobStatus.SUCCEEDED:
        raise Problem(409, "policy_not_ready", f"job {job_id} is {row.status}; a policy exists once it has succeeded")
    name, media = POLICY_FILES[fmt]
    folder = job_dir(settings, job_id) / "policy"
    path = folder / which / name
    if which == "last" and not path.is_file():
        path = folder / name  # a job that succeeded before runs exported both policies kept its only one here
    if not path.is_file():
        raise Problem(404, "not_found", f"job {job_id} has no {fmt} file for its {which} policy")
    return path, media
