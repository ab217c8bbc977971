"""Liveness and readiness probes."""
from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import text

from ..problems import problem_response
from ..schemas import Status

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Status, summary="The process is up")
def healthz() -> dict:
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
async def readyz(request: Request):
    problems = await run_in_threadpool(_check, request)
    if problems:
        return problem_response(503, "not_ready", "; ".join(problems))
    return {"status": "ready"}
