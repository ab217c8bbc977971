"""What the job routes read: a job by its owner (404 otherwise), the job list, a job's events and its outputs.

The hot reads (a job, the job list, a job's events) are statements built once and awaited through the API's
`FastReads` (kernel/fast_reads.py): on PostgreSQL they run on the event loop, with no thread hop and no ORM, the
job reads that start in one turn of the loop go as one statement (`FastReads.keyed`), and stored JSON (a job's config)
passes through unparsed. Their answers are sent as the dicts the serializers make, which already have the documented
shapes: validating them again against the response model would only spend the time twice. The other reads take the
request's ORM session.
"""
from __future__ import annotations

from pathlib import Path

from sqlalchemy import String, any_, bindparam, select
from sqlalchemy.dialects.postgresql import ARRAY
from sqlalchemy.orm import Session

from drop_engine.policy_files import FILE_NAMES, PolicyFormat
from drop_engine.scores import Which
from kernel.fast_reads import FastReads
from kernel.ids import is_id
from kernel.job_state import JobStatus
from kernel.models import Job, JobCheckpoint, JobEvaluation, JobEvent, JobMetric
from kernel.settings import Settings
from kernel.storage import from_stored, job_dir

from ..core.pages import fetch_page, page
from ..core.problems import Problem
from . import schemas

POLICY_FILES = {fmt: (name, "application/json" if fmt == "metadata" else "application/octet-stream")
                for fmt, name in FILE_NAMES.items()}

_JOB_COLUMNS = list(Job.__table__.c)
_OWNED = (Job.id == bindparam("job_id"), Job.owner_id == bindparam("owner"))
# Jobs by id, for batched reads (FastReads.keyed): an array on PostgreSQL, an expanding IN on SQLite.
JOBS_BY_ID = {True: select(*_JOB_COLUMNS).where(Job.id == any_(bindparam("keys", type_=ARRAY(String)))),
              False: select(*_JOB_COLUMNS).where(Job.id.in_(bindparam("keys", expanding=True)))}
JOB_EXISTS = select(Job.id).where(*_OWNED)
JOB_STATUS = select(Job.status).where(Job.id == bindparam("job_id"))
EVENTS = (select(JobEvent.__table__).where(JobEvent.job_id == bindparam("job_id"), JobEvent.id > bindparam("after"))
          .order_by(JobEvent.id).limit(bindparam("limit")))
# The owner's job with its events after the cursor, in one round trip: no row is a 404, one row of NULLs an empty page.
# The page is limited before the join, so the read walks `limit` index entries, not every event after the cursor
# (joined first, 100,000 events cost PostgreSQL a 31 ms scan and sort per page).
_PAGE = EVENTS.subquery()
OWNED_EVENTS = (select(Job.id.label("owned_job"), *_PAGE.c).select_from(Job)
                .outerjoin(_PAGE, _PAGE.c.job_id == Job.id).where(*_OWNED).order_by(_PAGE.c.id))


def _jobs_list(by_status: bool, paged: bool):
    q = select(*_JOB_COLUMNS).where(Job.owner_id == bindparam("owner"))
    if by_status:
        q = q.where(Job.status == bindparam("status"))
    if paged:
        q = q.where(Job.id < bindparam("after"))
    return q.order_by(Job.id.desc()).limit(bindparam("limit"))


JOBS = {(by_status, paged): _jobs_list(by_status, paged) for by_status in (False, True) for paged in (False, True)}


def _not_found(job_id: str) -> Problem:
    return Problem(404, "not_found", f"job {job_id} not found")


def owned_job(s: Session, owner_id: str, job_id: str) -> Job:
    """The owner's job or 404 (for the reads that hold an ORM session)."""
    q = select(Job).where(Job.id == job_id, Job.owner_id == owner_id)
    row = s.scalar(q) if is_id(job_id, "job") else None
    if row is None:
        raise _not_found(job_id)
    return row


async def check_owned(reads: FastReads, owner: str, job_id: str) -> None:
    """404 unless the job is the owner's."""
    if not is_id(job_id, "job") or await reads.one(JOB_EXISTS, job_id=job_id, owner=owner) is None:
        raise _not_found(job_id)


async def job(reads: FastReads, owner: str, job_id: str) -> dict:
    row = await reads.keyed(JOBS_BY_ID[reads.on_postgresql], "id", job_id) if is_id(job_id, "job") else None
    if row is None or row.owner_id != owner:
        raise _not_found(job_id)
    return schemas.job(row)


async def jobs_page(reads: FastReads, owner: str, status: JobStatus | None, after: str | None, limit: int) -> dict:
    params = {"owner": owner, "limit": limit + 1}
    if status is not None:
        params["status"] = status.value
    if after:
        params["after"] = after
    rows = await reads.all(JOBS[(status is not None, bool(after))], **params)
    return page([schemas.job(r) for r in rows[:limit]], len(rows) > limit)


async def events_page(reads: FastReads, owner: str, job_id: str, after: int, limit: int) -> dict:
    rows = await reads.all(OWNED_EVENTS, job_id=job_id, owner=owner, after=after, limit=limit + 1) if is_id(
        job_id, "job") else []
    if not rows:
        raise _not_found(job_id)
    events = [r for r in rows if r.id is not None]
    return page([schemas.event(r) for r in events[:limit]], len(events) > limit)


async def events_after(reads: FastReads, job_id: str, after: int, limit: int) -> tuple[list[dict], str | None]:
    """(events after `after`, the job's status), for the event stream. The status is read first: a final status
    commits together with its events, so when it is final here they are all in the rows read next, and the stream
    cannot end short of them."""
    status = await reads.one(JOB_STATUS, job_id=job_id)
    rows = await reads.all(EVENTS, job_id=job_id, after=after, limit=limit)
    return [schemas.event(r) for r in rows], status and status.status


def metrics_page(s: Session, owner: str, job_id: str, name: str | None, after: int, limit: int) -> dict:
    owned_job(s, owner, job_id)
    q = select(JobMetric).where(JobMetric.job_id == job_id, JobMetric.id > after)
    if name:
        q = q.where(JobMetric.name == name)
    return fetch_page(s, q.order_by(JobMetric.id), schemas.metric, limit)


def evaluations(s: Session, owner: str, job_id: str) -> list[JobEvaluation]:
    owned_job(s, owner, job_id)
    return list(s.scalars(select(JobEvaluation).where(JobEvaluation.job_id == job_id).order_by(JobEvaluation.id)))


def evaluations_page(s: Session, owner: str, job_id: str, after: int, limit: int) -> dict:
    owned_job(s, owner, job_id)
    q = select(JobEvaluation).where(JobEvaluation.job_id == job_id, JobEvaluation.id > after)
    return fetch_page(s, q.order_by(JobEvaluation.id), schemas.evaluation, limit)


def checkpoints_page(s: Session, owner: str, job_id: str, settings: Settings) -> dict:
    """The checkpoints still on disk (the trainer prunes older ones)."""
    owned_job(s, owner, job_id)
    rows = s.scalars(select(JobCheckpoint).where(JobCheckpoint.job_id == job_id).order_by(JobCheckpoint.id))
    return page([schemas.checkpoint(r) for r in rows if from_stored(settings, r.path).is_file()], False)


def _policy_path(folder: Path, which: Which, name: str) -> Path:
    path = folder / which / name
    if which == "last" and not path.is_file() and (folder / name).is_file():
        return folder / name  # a job that succeeded before runs exported both policies kept its only one here
    return path


def policy_file(s: Session, owner: str, job_id: str, which: Which, fmt: PolicyFormat,
                settings: Settings) -> tuple[Path, str]:
    """(path, media type) of the job's `which` policy in format `fmt`: 409 `policy_not_ready` while the job may still
    succeed, 409 `job_not_succeeded` once it failed or was cancelled (a script that waits on the first must stop on the
    second). 404 `policy_format_unavailable` for an ONNX file the export could not write (best effort: the job's
    events say why, and the other formats are there); 404 `policy_file_missing` for a file gone from the server."""
    row = owned_job(s, owner, job_id)
    if row.status in (JobStatus.FAILED, JobStatus.CANCELLED):
        raise Problem(409, "job_not_succeeded", f"job {job_id} is {row.status}: it has no policy and will have none")
    if row.status != JobStatus.SUCCEEDED:
        raise Problem(409, "policy_not_ready", f"job {job_id} is {row.status}; its policy is ready once it succeeds")
    name, media = POLICY_FILES[fmt]
    folder = job_dir(settings, job_id) / "policy"
    path = _policy_path(folder, which, name)
    if not path.is_file():
        if fmt == "onnx" and _policy_path(folder, which, POLICY_FILES["torchscript"][0]).is_file():
            raise Problem(404, "policy_format_unavailable", f"job {job_id}'s {which} policy has no ONNX file: its "
                          "export to ONNX failed (the job's events say why); format=torchscript or state_dict has it")
        raise Problem(404, "policy_file_missing", f"job {job_id} succeeded, but the {fmt} file of its {which} policy "
                      "is no longer on the server")
    return path, media
