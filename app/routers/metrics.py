"""Prometheus scrape endpoint."""
from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST

from ..metrics import exposition

router = APIRouter(tags=["health"])


@router.get("/metrics", response_class=Response, summary="Prometheus metrics: HTTP, uploads, jobs (text format)",
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
def metrics(request: Request) -> Response:
    return Response(exposition(request.app.state.job_metrics), media_type=CONTENT_TYPE_LATEST)
