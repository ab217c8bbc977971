"""Jobs: create (idempotent), list, get, cancel, delete."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response

from kernel.job_state import JobStatus

from ..core.deps import AppSettings, DbSession, JobCursor, OwnerId
from ..core.fast_json import FastJSONResponse
from ..core.pages import Page
from . import reads, service
from .request import JobRequest
from .schemas import JobOut, job

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])


@router.post("", status_code=201, response_model=JobOut, summary="Create a training job",
             responses={200: {"description": "A replay: the job an earlier request with this Idempotency-Key made",
                              "model": JobOut}})
def jobs_create(req: JobRequest, request: Request, response: Response, owner: OwnerId, s: DbSession,
                settings: AppSettings,
                idempotency_key: Annotated[str | None, Header(min_length=1, max_length=200)] = None) -> dict:
    row, created = service.create(s, owner, req, idempotency_key, settings, request.app.state.enqueue)
    if not created:
        response.status_code = 200
    return job(row)


@router.get("", response_model=Page[JobOut], summary="List jobs, newest first")
async def jobs_list(request: Request, owner: OwnerId, status: JobStatus | None = None, after: JobCursor = None,
                    limit: Annotated[int, Query(ge=1, le=100)] = 20) -> FastJSONResponse:
    return FastJSONResponse(await reads.jobs_page(request.app.state.fast_reads, owner, status, after, limit))


@router.get("/{job_id}", response_model=JobOut)
async def jobs_get(job_id: str, request: Request, owner: OwnerId) -> FastJSONResponse:
    return FastJSONResponse(await reads.job(request.app.state.fast_reads, owner, job_id))


@router.post("/{job_id}/cancel", status_code=202, response_model=JobOut,
             summary="Cancel: a queued job at once, a running one at its next step",
             responses={200: {"description": "Cancelled: a queued job by this request, or any job before it",
                              "model": JobOut}})
def jobs_cancel(job_id: str, response: Response, owner: OwnerId, s: DbSession) -> dict:
    """The code follows the job's status: 202 while it stops (cancelling), 200 once it is cancelled, so a client
    polls only after a 202. Safe to repeat: asking again changes nothing. A job that succeeded or failed: 409."""
    row = service.cancel(s, owner, job_id)
    if row.status == JobStatus.CANCELLED:
        response.status_code = 200
    return job(row)


@router.delete("/{job_id}", status_code=204,
               summary="Delete a finished job with its checkpoints, policies and records (409 until it has finished)")
def jobs_delete(job_id: str, owner: OwnerId, s: DbSession, settings: AppSettings) -> Response:
    service.delete(s, owner, job_id, settings)
    return Response(status_code=204)
