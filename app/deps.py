"""Request-scoped dependencies: settings, a database session, the owner, and owner-scoped lookups (404 otherwise)."""
from __future__ import annotations

from typing import Annotated, Iterator

from fastapi import Depends, Query, Request
from sqlalchemy import select
from sqlalchemy.orm import Session, defer

from .auth import current_owner
from kernel.ids import id_pattern, is_id
from kernel.models import Dataset, Job
from .problems import Problem
from kernel.settings import Settings


def settings(request: Request) -> Settings:
    return request.app.state.settings


def session(request: Request) -> Iterator[Session]:
    with request.app.state.sessions() as s:
        yield s


def owned_dataset(s: Session, owner_id: str, dataset_id: str) -> Dataset:
    """The owner's dataset or 404."""
    q = select(Dataset).where(Dataset.id == dataset_id, Dataset.owner_id == owner_id)
    row = s.scalar(q) if is_id(dataset_id, "ds") else None
    if row is None:
        raise Problem(404, "not_found", f"dataset {dataset_id} not found")
    return row


def owned_job(s: Session, owner_id: str, job_id: str) -> Job:
    # The API never shows a job's `result` (the engine's full report), so it is not read.
    q = select(Job).where(Job.id == job_id, Job.owner_id == owner_id).options(defer(Job.result))
    row = s.scalar(q) if is_id(job_id, "job") else None
    if row is None:
        raise Problem(404, "not_found", f"job {job_id} not found")
    return row


def _cursor(prefix: str):
    """The type of a list's `?after=`: an id, as the previous page's `next_after` gave it; anything else is a 422."""
    return Annotated[str | None, Query(pattern=id_pattern(prefix), description="`next_after` of the previous page")]


DatasetCursor = _cursor("ds")
JobCursor = _cursor("job")
Owner = Depends(current_owner)
# Closed as soon as the endpoint returns, before the response is sent: a streamed response (the event stream) must
# not keep a pooled connection for its whole life.
DB = Depends(session, scope="function")
Config = Depends(settings)
