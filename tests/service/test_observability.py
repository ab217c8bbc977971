"""/metrics moves with a real job (HTTP, uploads, jobs from the database, the dynamics cache), a request's id goes
round trip and onto its log lines, and a worker's log lines carry the job, attempt and worker."""
from __future__ import annotations

import io
import json
import logging
import os
import time
from datetime import datetime, timedelta

import pytest
from fastapi.testclient import TestClient

from .processes import kill_group, start_worker
from .scrapes import sample


@pytest.fixture
def served(own_settings, tmp_path):
    """An app and a worker of the test's own, on a database of its own, so every count is the test's."""
    from app.core.auth import create_token
    from app.main import create_app

    app = create_app(own_settings)
    token = create_token(app.state.sessions, "metrics")
    worker = start_worker(own_settings, tmp_path / "worker.log")
    try:
        with TestClient(app, headers={"Authorization": f"Bearer {token}"}) as client:
            yield client, tmp_path / "worker.log"
    finally:
        kill_group(worker)
        app.state.engine.dispose()


def test_metrics_move_during_a_smoke_job(served, hopper_file):
    client, worker_log = served
    before = client.get("/metrics")
    assert before.status_code == 200 and before.headers["content-type"].startswith("text/plain")
    before = before.text

    refused = client.post("/v1/datasets", content=b"not a dataset", headers={"Content-Type": "application/x-hdf5"})
    assert refused.status_code == 422
    ds = client.post("/v1/datasets", files={"file": ("h.hdf5", hopper_file.read_bytes())}).json()
    job = client.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke"}).json()
    during = client.get("/metrics").text
    unfinished = sum(sample(during, "drop_jobs", status=s) for s in ("queued", "running", "cancelling"))
    assert unfinished == 1, during
    for _ in range(480):
        status = client.get(f"/v1/jobs/{job['id']}").json()["status"]
        if status in ("succeeded", "failed", "cancelled"):
            break
        time.sleep(0.25)
    assert status == "succeeded"
    after = client.get("/metrics").text

    def moved(name: str, **labels: str) -> float:
        return sample(after, name, **labels) - sample(before, name, **labels)

    assert moved("drop_jobs", status="succeeded") == 1
    assert moved("drop_job_attempts") == 1
    assert moved("drop_job_queue_wait_seconds_count") == 1 and moved("drop_job_run_seconds_count") == 1
    assert moved("drop_job_run_seconds_sum") > 0
    assert moved("drop_dynamics_cache_lookups_total", result="hit") + moved(
        "drop_dynamics_cache_lookups_total", result="miss") == 1
    assert moved("drop_http_requests_total", method="GET", route="/v1/jobs/{job_id}", status="200") >= 1
    assert moved("drop_http_request_duration_seconds_count", method="POST", route="/v1/jobs", status="201") == 1
    assert moved("drop_upload_bytes_total") == hopper_file.stat().st_size + len(b"not a dataset")
    assert moved("drop_upload_validation_duration_seconds_count") == 2
    assert moved("drop_upload_rejections_total", code="invalid_dataset") == 1

    lines = [json.loads(line) for line in worker_log.read_text().splitlines() if line.startswith("{")]
    mine = [line for line in lines if line.get("job_id") == job["id"]]
    assert mine and all(line["attempt"] == 1 and line["worker"] for line in mine), lines[-20:]
    assert any("ended: succeeded" in line["event"] for line in mine)


@pytest.fixture
def json_logs():
    """JSON log lines, as `drop api` writes them to stderr, captured here; logging is restored afterwards."""
    from kernel import logs

    root = logging.getLogger()
    saved = root.handlers[:], root.level, logs.access_line
    logs.configure("json", "INFO")
    out = io.StringIO()
    root.handlers[0].setStream(out)
    def once(pairs: list[tuple[str, object]]) -> dict:
        assert len({k for k, _ in pairs}) == len(pairs), f"a key written twice: {pairs}"
        return dict(pairs)

    def lines() -> list[dict]:
        logs.flush_access()  # access lines wait up to ACCESS_FLUSH_S
        return [json.loads(line, object_pairs_hook=once) for line in out.getvalue().splitlines()]

    try:
        yield lines
    finally:
        root.handlers, root.level, logs.access_line = saved


def test_the_written_access_line_is_the_logged_one(json_logs):
    """The access line skips the logging module (kernel/logs.py); what it writes is what a record would have."""
    import structlog

    from kernel import logs

    assert logs.access_line is not logs._access_through_logging
    # `status` as a bound name too: the line's own field wins, and the key is written once
    with structlog.contextvars.bound_contextvars(request_id="r-1", job_id="job_1", attempt=2, status="bound"):
        logs.access_line("GET", "/v1/jobs/ünï", 404, 1.5)
        logs._access_through_logging("GET", "/v1/jobs/ünï", 404, 1.5)
    written, logged = json_logs()
    # The same form and about the same time (a prefix compared to the minute differed across a minute's turn).
    stamps = [line.pop("timestamp") for line in (written, logged)]
    assert [len(s) for s in stamps] == [len(stamps[0])] * 2 and all(s.endswith("Z") for s in stamps), stamps
    times = [datetime.fromisoformat(s.replace("Z", "+00:00")) for s in stamps]
    assert abs(times[1] - times[0]) < timedelta(seconds=30), stamps
    assert written == logged and written["request_id"] == "r-1" and written["path"] == "/v1/jobs/ünï"
    assert written["status"] == 404


def test_log_lines_follow_stderr_once_it_is_swapped(monkeypatch):
    """The handler writes to the stderr of the moment: one made before stderr was swapped and closed (pytest's
    capture between tests) neither writes to the closed file nor prints logging's error traceback."""
    from kernel import logs

    root = logging.getLogger()
    saved = root.handlers[:], root.level, logs.access_line
    first, second, errors = io.StringIO(), io.StringIO(), []
    try:
        monkeypatch.setattr("sys.stderr", first)
        logs.configure("json", "INFO")
        monkeypatch.setattr(logging.Handler, "handleError", lambda self, record: errors.append(record))
        first.close()
        monkeypatch.setattr("sys.stderr", second)
        logging.getLogger("drop.test").info("after the swap")
        logs.access_line("GET", "/healthz", 200, 0.1)
        logs.flush_access()
    finally:
        root.handlers, root.level, logs.access_line = saved
    lines = [json.loads(line) for line in second.getvalue().splitlines()]
    assert not errors and [line["event"] for line in lines] == ["after the swap", "request"]


def test_request_ids_are_redrawn_in_a_forked_child():
    """`drop api --workers N` forks: a child must not count on from its parent's prefix."""
    from app.observability.observe import IDS

    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child writes its id and leaves at once, whatever happens: never back into pytest
        try:
            os.write(write, IDS.new().encode())
        finally:
            os._exit(0)
    try:
        os.waitpid(pid, 0)
        child, parent = os.read(read, 64).decode(), IDS.new()
    finally:
        os.close(read)
        os.close(write)
    assert len(child) == len(parent) == 32 and child[:16] != parent[:16]


def test_request_id_round_trip_and_on_log_lines(client, alice, json_logs):
    r = alice.get("/v1/jobs", headers={"X-Request-ID": "trace-42.a"})
    assert r.status_code == 200 and r.headers["x-request-id"] == "trace-42.a"
    fresh = client.get("/healthz").headers["x-request-id"]
    assert len(fresh) == 32 and fresh != "trace-42.a"
    for bad in ("has space", "x" * 200, "ünïcode".encode("latin-1")):
        assert client.get("/healthz", headers={"X-Request-ID": bad}).headers["x-request-id"] not in (bad, fresh)
    missing = alice.get("/v1/jobs/job_nope", headers={"X-Request-ID": "trace-43"})
    assert missing.status_code == 404 and missing.headers["x-request-id"] == "trace-43"

    lines = json_logs()
    access = {line["request_id"]: line for line in lines if line.get("logger") == "drop.access"}
    assert access["trace-42.a"]["status"] == 200 and access["trace-42.a"]["path"] == "/v1/jobs"
    assert access["trace-43"]["status"] == 404 and access[fresh]["path"] == "/healthz"
    assert {"timestamp", "level", "ms", "method"} <= access["trace-42.a"].keys()


def test_access_lines_go_out_together_within_the_flush_interval(json_logs):
    """On the event loop, access lines wait up to ACCESS_FLUSH_S and are then written in one go."""
    import asyncio

    from kernel import logs

    stream = logging.getLogger().handlers[0].stream

    async def serve() -> tuple[str, str]:
        for n in range(3):
            logs.access_line("GET", f"/r{n}", 200, 0.1)
        before = stream.getvalue()
        await asyncio.sleep(logs.ACCESS_FLUSH_S + 0.2)
        return before, stream.getvalue()

    before, after = asyncio.run(serve())
    assert before == "" and [line["path"] for line in json_logs()] == ["/r0", "/r1", "/r2"]
    assert after.count("\n") == 3
