"""Per-owner quotas: unfinished jobs (429) and stored dataset bytes (413).

Each check counts under the owner's lock (app/owners/lock.py), so two requests of one owner at once cannot both count
the same total and both slip past. On a refusal the transaction is rolled back at once, which frees the lock. A
dataset counts at the larger of its file size and its decoded size (`Dataset.charged_bytes`).
"""
from __future__ import annotations

from typing import Callable

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from kernel.job_state import ACTIVE, status_in
from kernel.models import Dataset, Job
from kernel.settings import Settings

from ..core.problems import Problem
from .lock import lock_owner

RETRY_AFTER_S = 60  # jobs take minutes; asking again sooner is pointless


def _refuse(s: Session, problem: Problem) -> Problem:
    s.rollback()
    return problem


def check_active_jobs(s: Session, owner_id: str, settings: Settings) -> None:
    """Raise 429 if the owner already has the most unfinished jobs allowed; the lock lasts until the caller commits."""
    lock_owner(s, owner_id)
    active = s.scalar(select(func.count()).select_from(Job)
                      .where(Job.owner_id == owner_id, status_in(ACTIVE)))
    limit = settings.max_active_jobs_per_owner
    if active >= limit:
        raise _refuse(s, Problem(
            429, "job_quota_exceeded",
            f"you have {active} unfinished jobs (queued, running or cancelling) and at most {limit} are allowed "
            "at once (DROP_MAX_ACTIVE_JOBS_PER_OWNER); wait for one to finish or cancel one",
            headers={"Retry-After": str(RETRY_AFTER_S)}))


def stored_bytes(s: Session, owner_id: str) -> int:
    return s.scalar(select(func.coalesce(func.sum(Dataset.charged_bytes), 0)).where(Dataset.owner_id == owner_id))


def _storage_problem(stored: int, quota: int, detail: str) -> Problem:
    return Problem(413, "storage_quota_exceeded",
                   f"{detail}: your datasets take {stored} of the {quota} bytes allowed per owner "
                   "(DROP_MAX_STORED_BYTES_PER_OWNER); delete datasets you no longer need to make room")


def upload_limit(s: Session, owner_id: str, settings: Settings) -> tuple[int, Callable[[], Problem] | None]:
    """The most bytes the owner's next upload may have, and the problem to raise past it (None: the plain upload
    limit). Ends the session's transaction, so no connection is held while the upload streams."""
    stored = stored_bytes(s, owner_id)
    s.close()
    quota = settings.max_stored_bytes_per_owner
    room = max(quota - stored, 0)
    if room >= settings.max_upload_bytes:
        return settings.max_upload_bytes, None
    return room, lambda: _storage_problem(stored, quota, f"this upload is larger than the {room} bytes left")


def check_storage(s: Session, owner_id: str, settings: Settings, row: Dataset) -> None:
    """Raise 413 if the new dataset `row` takes the owner past the quota (recounted under the owner lock, as uploads
    of one owner may run side by side); the lock lasts until the caller commits."""
    lock_owner(s, owner_id)
    stored, quota = stored_bytes(s, owner_id), settings.max_stored_bytes_per_owner
    if stored + row.charged_bytes > quota:
        detail = (f"this {row.size_bytes}-byte dataset does not fit" if row.charged_bytes == row.size_bytes else
                  f"this dataset counts {row.charged_bytes} bytes, its decoded size ({row.size_bytes} bytes on disk), "
                  "and does not fit")
        raise _refuse(s, _storage_problem(stored, quota, detail))
