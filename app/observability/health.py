"""What operators poll: liveness and readiness probes, and the Prometheus scrape endpoint."""
from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool
from prometheus_client import CONTENT_TYPE_LATEST
from pydantic import BaseModel
from sqlalchemy import text

from ..core.problems import problem_response
from .metrics import exposition

router = APIRouter(tags=["health"])


class Status(BaseModel):
    status: str


@router.get("/healthz", response_model=Status, summary="The process is up")
async def health_live() -> dict:
    """On the event loop, not in the threadpool: the process is up when its loop answers, and the probe costs no
    thread hop (it is the benchmark's measure of what the framework alone can serve)."""
    return {"status": "ok"}


def _check(request: Request) -> list[str]:
    problems = []
    try:
        with request.app.state.engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except Exception as exc:
        problems.append(f"database: {type(exc).__name__}")
    try:
        with request.app.state.celery.connection_for_write() as conn:
            conn.ensure_connection(max_retries=1, timeout=2)
    except Exception as exc:
        problems.append(f"broker: {type(exc).__name__}")
    return problems


@router.get("/readyz", response_model=Status, summary="The database and the broker are reachable")
async def health_ready(request: Request):
    problems = await run_in_threadpool(_check, request)
    if problems:
        return problem_response(503, "not_ready", "; ".join(problems))
    return {"status": "ready"}


@router.get("/metrics", response_class=Response, summary="Prometheus metrics: HTTP, uploads, jobs (text format)",
            responses={200: {"content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}}}})
def health_metrics(request: Request) -> Response:
    return Response(exposition(request.app.state.job_metrics), media_type=CONTENT_TYPE_LATEST)
