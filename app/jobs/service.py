"""The service behind /v1/jobs: creating a job (idempotent per Idempotency-Key, within the dataset's shape and the
server's limits and the owner's quota) and sending it to the workers, cancelling one, and deleting a finished one."""
from __future__ import annotations

import hashlib
import json
import logging

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from kernel import job_state
from kernel.ids import new_id
from kernel.job_state import JobStatus, mark_sent, transition
from kernel.models import DeletedJob, Job, utcnow
from kernel.queue import Enqueue
from kernel.settings import Settings
from kernel.storage import job_dir, remove_tree

from ..core.problems import Problem
from ..datasets.service import owned_dataset
from ..owners import quotas
from ..owners.lock import lock_owner
from .reads import owned_job
from .request import JobRequest, build

log = logging.getLogger("drop.api")


def _request_hash(req: JobRequest) -> str:
    return hashlib.sha256(json.dumps(req.model_dump(mode="json"), sort_keys=True).encode()).hexdigest()


def _replay(s: Session, owner: str, key: str, digest: str) -> Job | None:
    row = s.scalar(select(Job).where(Job.owner_id == owner, Job.idempotency_key == key))
    if row is not None and row.request_hash != digest:
        raise Problem(422, "idempotency_key_reused",
                      f"Idempotency-Key {key!r} was already used with a different request body")
    return row


def create(s: Session, owner: str, req: JobRequest, idempotency_key: str | None, settings: Settings,
           enqueue: Enqueue) -> tuple[Job, bool]:
    """(the job, whether this request created it): a request that repeats an earlier one's Idempotency-Key and body
    gets that request's job."""
    digest = _request_hash(req)
    lock_owner(s, owner)  # before the dataset is read: a delete of it either finished first (404) or waits (409)
    # Under the lock: a request with this key that held it before may have created the job, and its replay is that
    # job, not a 429 for the place it took or a 404 for a dataset deleted since.
    if idempotency_key and (existing := _replay(s, owner, idempotency_key, digest)) is not None:
        return existing, False
    dataset = owned_dataset(s, owner, req.dataset_id)
    env, config = build(req, dataset, settings)
    quotas.check_active_jobs(s, owner, settings)
    job = Job(id=new_id("job"), owner_id=owner, dataset_id=dataset.id, algorithm=config["algorithm"], env=env,
              preset=config["preset"], overrides=req.overrides, seed=req.seed, config=config,
              max_attempts=settings.max_attempts, max_runtime_s=req.max_runtime_s or settings.max_runtime_s,
              idempotency_key=idempotency_key, request_hash=digest)
    try:
        job_state.create(s, job)
        s.commit()
    except IntegrityError:  # the same key at once from another request, which committed first
        s.rollback()
        existing = _replay(s, owner, idempotency_key or "", digest) if idempotency_key else None
        if existing is None:
            raise
        return existing, False
    try:
        enqueue(job.id, job.max_runtime_s)
    except Exception:  # the reaper re-sends jobs never enqueued, so a broker hiccup delays the job but loses nothing
        log.exception("could not enqueue job %s; the reaper will retry", job.id)
    else:
        mark_sent(s, job.id, utcnow())
        s.commit()
    return job, True


def cancel(s: Session, owner: str, job_id: str) -> Job:
    """A queued job is cancelled at once, a running one becomes cancelling until its worker stops it at the next
    step; asking again changes nothing. 409 once it succeeded or failed."""
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
    return job


def delete(s: Session, owner: str, job_id: str, settings: Settings) -> None:
    """Delete a finished job: its row, with its events, metrics, evaluations and checkpoint rows (the foreign keys
    cascade), then its folder of checkpoints and policies; what /metrics counts of it stays (`DeletedJob`). 409
    while it is queued, running or cancelling, as a worker may still write there: cancel it first. The rows go
    before the files, so a crash between them leaves an unlisted folder, never a listed job whose files are gone."""
    lock_owner(s, owner)  # ordered against a create that would replay this job's Idempotency-Key
    row = owned_job(s, owner, job_id)
    if row.status not in job_state.FINAL:
        raise Problem(409, "job_not_finished",
                      f"job {job_id} is {row.status}; cancel it and wait until it is cancelled, then delete it")
    s.add(DeletedJob(id=row.id, attempts=row.attempts, queue_wait_s=row.queue_wait_s, run_s=row.run_s,
                     dynamics_from_cache=row.dynamics_from_cache))  # /metrics keeps counting it
    s.delete(row)
    s.commit()
    remove_tree(job_dir(settings, job_id))
