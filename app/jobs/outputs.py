"""What a job produces: events (paged or as a server-sent event stream), metrics, evaluations, checkpoints, the
learning curve and the trained policy."""
from __future__ import annotations

import json
import os
import time
from functools import partial
from typing import Annotated, Callable

from fastapi import APIRouter, Query, Request, Response
from fastapi.responses import FileResponse, StreamingResponse
from starlette.background import BackgroundTask

from drop_engine.plots import learning_curve
from drop_engine.policy_files import PolicyFormat
from drop_engine.scores import Which
from kernel.fast_reads import FastReads
from kernel.job_state import FINAL

from ..core.deps import AppSettings, DbSession, OwnerId
from ..core.fast_json import FastJSONResponse, dumps
from ..core.openapi import BINARY
from ..core.pages import Page
from . import reads
from .schemas import CheckpointOut, EvaluationOut, EventOut, MetricOut, PolicyMetadata

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["job outputs"])
SSE_POLL_S = 0.5
SSE_KEEPALIVE_S = 15.0
MAX_ROW_ID = 2**63 - 1  # event, metric and evaluation ids are 64-bit columns: a larger cursor is a 422, not a 500
After = Annotated[int, Query(ge=0, le=MAX_ROW_ID, description="only rows with a larger id (the cursor)")]
RowLimit = Annotated[int, Query(ge=1, le=10000)]  # rows of a page of metrics or evaluations


# What may not appear raw in an event's one `data:` line. A stored JSON column passes through as its text, where a line
# break can only be whitespace, so it becomes a space. orjson writes non-ASCII as is, and clients that split lines with
# str.splitlines (httpx's iter_lines) also break at NEL and the Unicode line and paragraph separators, which JSON
# allows only inside strings, where their escapes mean the same.
_ONE_LINE = str.maketrans({"\n": " ", "\r": " ", "\x85": "\\u0085", "\u2028": "\\u2028", "\u2029": "\\u2029"})


def sse_event(item: dict) -> str:
    """An event as one server-sent event: its id, type and JSON on a single data line."""
    return f"id: {item['id']}\nevent: {item['type']}\ndata: {dumps(item).decode().translate(_ONE_LINE)}\n\n"


async def _frames(fast_reads: FastReads, job_id: str, after: int) -> tuple[list[tuple[int, str]], str | None]:
    """(event id, its SSE frame) of the events after `after`, and the job's status: made once for all the streams
    that share the read."""
    items, status = await reads.events_after(fast_reads, job_id, after, 500)
    return [(item["id"], sse_event(item)) for item in items], status


async def _stream(request: Request, job_id: str, after: int, release: Callable[[], None]):
    """Events after `after` until the job ends. Each read takes a pooled connection only for its query; in between the
    stream waits for the job's next notification (PostgreSQL) or polls every SSE_POLL_S (SQLite, or listener down)."""
    state = request.app.state
    fast_reads, waker = state.fast_reads, state.events
    try:
        with waker.subscribe(job_id) as topic:
            quiet = 0.0
            while True:
                seen = topic.version
                frames, status = await state.shared_reads.run((job_id, after, topic.serial, seen),
                                                              partial(_frames, fast_reads, job_id, after))
                for _, frame in frames:
                    yield frame
                if frames:
                    after = frames[-1][0]
                    quiet = 0.0
                    continue
                if status in FINAL or status is None:
                    yield f"event: end\ndata: {json.dumps({'status': status})}\n\n"
                    return
                if await request.is_disconnected():
                    return
                began = time.monotonic()
                await waker.wait(topic, seen, SSE_KEEPALIVE_S - quiet if waker.live else SSE_POLL_S)
                quiet += time.monotonic() - began
                if quiet >= SSE_KEEPALIVE_S:
                    quiet = 0.0
                    yield ": keep-alive\n\n"
    finally:
        release()


@router.get("/events", response_model=Page[EventOut],
            summary="Job events, oldest first; `Accept: text/event-stream` streams them until the job ends",
            responses={200: {"content": {"text/event-stream": {"schema": {"type": "string"}}}}})
async def jobs_get_events(job_id: str, request: Request, owner: OwnerId, after: After = 0,
                          limit: Annotated[int, Query(ge=1, le=1000)] = 100):
    fast_reads = request.app.state.fast_reads
    if "text/event-stream" not in request.headers.get("accept", ""):
        return FastJSONResponse(await reads.events_page(fast_reads, owner, job_id, after, limit))
    await reads.check_owned(fast_reads, owner, job_id)
    last = request.headers.get("last-event-id", "")
    start = int(last) if last.isascii() and last.isdigit() and int(last) <= MAX_ROW_ID else after
    release = request.app.state.stream_slots.take(owner)
    # The stream's own `finally` gives the slot back, and so does the background task in case the stream is never
    # started (the client left first).
    return StreamingResponse(_stream(request, job_id, start, release), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
                             background=BackgroundTask(release))


@router.get("/metrics", response_model=Page[MetricOut], summary="Scalar training metrics, oldest first; filter by name")
def jobs_get_metrics(job_id: str, owner: OwnerId, s: DbSession,
                     name: Annotated[str | None, Query(max_length=100, pattern=r"^[^\x00]*$")] = None,
                     after: After = 0, limit: RowLimit = 1000) -> dict:
    return reads.metrics_page(s, owner, job_id, name, after, limit)


@router.get("/evaluations", response_model=Page[EvaluationOut],
            summary="Evaluations in the real env (return and D4RL normalised score)")
def jobs_get_evaluations(job_id: str, owner: OwnerId, s: DbSession, after: After = 0,
                         limit: RowLimit = 1000) -> dict:
    return reads.evaluations_page(s, owner, job_id, after, limit)


@router.get("/checkpoints", response_model=Page[CheckpointOut],
            summary="Checkpoints still on disk, keep_checkpoints of them (the trainer prunes older ones), so one "
                    "page")
def jobs_get_checkpoints(job_id: str, owner: OwnerId, s: DbSession, settings: AppSettings) -> dict:
    return reads.checkpoints_page(s, owner, job_id, settings)


@router.get("/curve.png", summary="Learning curve (normalised score per evaluation)", response_class=Response,
            responses={200: {"content": {"image/png": {"schema": BINARY}}}})
def jobs_get_curve(job_id: str, owner: OwnerId, s: DbSession) -> Response:
    rows = reads.evaluations(s, owner, job_id)
    png = learning_curve(job_id, [r.epoch for r in rows], [r.normalized_score for r in rows])
    return Response(png, media_type="image/png")


@router.get("/policy", summary="A trained policy, last or best: TorchScript or ONNX (obs batch -> actions), "
                               "state_dict, or metadata", response_class=FileResponse,
            responses={200: {"description": "The file: binary, or JSON for `format=metadata`", "model": PolicyMetadata,
                             "content": {"application/octet-stream": {"schema": BINARY}}},
                       304: {"description": "Not modified: the If-None-Match header holds the file's ETag"}})
def jobs_get_policy(job_id: str, request: Request, owner: OwnerId, s: DbSession, settings: AppSettings,
                    which: Annotated[Which, Query(description="last: the policy after the final epoch; best: the one "
                                                              "of the evaluation with the highest normalised score "
                                                              "(the earlier of ties), chosen by evaluations in the "
                                                              "real env")] = "last",
                    format: PolicyFormat = "torchscript"):
    """Conditional: a client that sends the ETag it has (If-None-Match) gets 304 and no body; HEAD gets the headers
    (size, ETag) alone; Range requests get the part asked for."""
    path, media = reads.policy_file(s, owner, job_id, which, format, settings)
    response = FileResponse(path, media_type=media, filename=f"{job_id}-{which}-{path.name}",
                            stat_result=os.stat(path))  # sets the ETag now, so it can be compared
    etag = response.headers["etag"]
    held = {tag.strip().removeprefix("W/") for tag in ",".join(request.headers.getlist("if-none-match")).split(",")}
    if etag in held or "*" in held:
        return Response(status_code=304, headers={"etag": etag})
    return response


router.add_api_route("/policy", jobs_get_policy, methods=["HEAD"], include_in_schema=False)
