"""Jobs: create (idempotent), list, get, cancel."""
from __future__ import annotations

import hashlib
import json
import logging

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from .. import quotas, reads, serialize
from ..deps import DB, Config, Owner, JobCursor, owned_dataset, owned_job
from kernel.ids import new_id
from ..jobcreate import JobRequest, build
from kernel.job_state import JobStatus, create, mark_sent, transition
from kernel.models import Job, utcnow
from ..owner_lock import lock_owner
from ..problems import Problem
from ..schemas import JobOut, Page
from kernel.settings import Settings

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])
log = logging.getLogger("drop.api")


def _request_hash(req: JobRequest) -> str:
    return hashlib.sha256(json.dumps(req.model_dump(mode="json"), sort_keys=True).encode()).hexdigest()


def _replay(s: Session, owner: str, key: str, digest: str) -> Job | None:
    row = s.scalar(select(Job).where(Job.owner_id == owner, Job.idempotency_key == key))
    if row is not None and row.request_hash != digest:
        raise Problem(422, "idempotency_key_reused",
                      f"Idempotency-Key {key!r} was already used with a different request body")
    return row


@router.post("", status_code=201, response_model=JobOut, summary="Create a training job",
             responses={200: {"description": "A replay: the job an earlier request with this Idempotency-Key made",
                              "model": JobOut}})
def create_job(req: JobRequest, request: Request, response: Response,
               idempotency_key: str | None = Header(None, min_length=1, max_length=200),
               owner: str = Owner, s: Session = DB, settings: Settings = Config) -> dict:
    digest = _request_hash(req)
    if idempotency_key:
        existing = _replay(s, owner, idempotency_key, digest)
        if existing is not None:
            response.status_code = 200
            return serialize.job(existing)
    lock_owner(s, owner)  # before the dataset is read: a delete of it either finished first (404) or waits (409)
    dataset = owned_dataset(s, owner, req.dataset_id)
    env, config = build(req, dataset, settings)
    quotas.check_active_jobs(s, owner, settings)
    job = Job(id=new_id("job"), owner_id=owner, dataset_id=dataset.id, algorithm=config["algorithm"], env=env,
              preset=config["preset"], overrides=req.overrides, seed=req.seed, config=config,
              max_attempts=settings.max_attempts, max_runtime_s=req.max_runtime_s or settings.max_runtime_s,
              idempotency_key=idempotency_key, request_hash=digest)
    try:
        create(s, job)
        s.commit()
    except IntegrityError:
        s.rollback()
        existing = _replay(s, owner, idempotency_key or "", digest) if idempotency_key else None
        if existing is None:
            raise
        response.status_code = 200
        return serialize.job(existing)
    try:
        request.app.state.enqueue(job.id, job.max_runtime_s)
    except Exception:  # the reaper re-sends jobs never enqueued, so a broker hiccup delays the job but loses nothing
        log.exception("could not enqueue job %s; the reaper will retry", job.id)
    else:
        mark_sent(s, job.id, utcnow())
        s.commit()
    return serialize.job(job)


@router.get("", response_model=Page[JobOut], summary="List jobs, newest first")
async def list_jobs(request: Request, status: str | None = Query(None, description=" | ".join(JobStatus)),
                    after: JobCursor = None, limit: int = Query(20, ge=1, le=100), owner: str = Owner) -> JSONResponse:
    return JSONResponse(await run_in_threadpool(reads.jobs_page, request.app.state.reader, owner, status, after,
                                                limit))


@router.get("/{job_id}", response_model=JobOut)
async def get_job(job_id: str, request: Request, owner: str = Owner) -> JSONResponse:
    return JSONResponse(await run_in_threadpool(reads.job, request.app.state.reader, owner, job_id))


@router.post("/{job_id}/cancel", status_code=202, response_model=JobOut,
             summary="Cancel: a queued job at once, a running one at its next step",
             responses={200: {"description": "Already cancelled: nothing changed", "model": JobOut}})
def cancel_job(job_id: str, response: Response, owner: str = Owner, s: Session = DB) -> dict:
    """Safe to repeat: asking again while it stops answers 202 again, and once it is cancelled 200; nothing changes.
    A job that succeeded or failed cannot be cancelled: 409."""
    owned_job(s, owner, job_id)
    done = transition(s, job_id, JobStatus.CANCELLED, source=JobStatus.QUEUED, values={"finished_at": utcnow()},
                      message="cancelled before it started")
    if not done:
        transition(s, job_id, JobStatus.CANCELLING, message="cancellation requested")
    s.commit()
    s.expire_all()
    job = owned_job(s, owner, job_id)
    if job.status in (JobStatus.SUCCEEDED, JobStatus.FAILED):
        raise Problem(409, "job_finished", f"job {job_id} has already finished ({job.status}); it cannot be cancelled")
    if job.status == JobStatus.CANCELLED and not done:
        response.status_code = 200
    return serialize.job(job)
