"""drop_client against a scripted server (httpx.MockTransport): typed errors, paging, the event stream, waiting and
downloads. tests/service/test_remote.py runs it against real deployments."""
from __future__ import annotations

import json

import httpx
import pytest

from drop_client import (ApiError, Conflict, DropClient, DropError, NetworkError, RateLimited, ServerError,
                         StreamInterrupted, Unprocessable, WaitTimeout)


def _client(handler, token: str | None = "secret") -> DropClient:
    http = httpx.Client(base_url="http://drop.test", transport=httpx.MockTransport(handler))
    return DropClient(token=token, http=http)


def _problem(status: int, code: str, detail: str, **extra) -> httpx.Response:
    return httpx.Response(status, json={"type": f"urn:drop-rl:problem:{code}", "title": "x", "status": status,
                                        "detail": detail, "code": code, **extra},
                          headers={"Content-Type": "application/problem+json", **extra.pop("headers", {})})


def _job(status: str, **fields) -> dict:
    return {"id": "job_1", "status": status, "progress": None, "last_score": None, "best_score": None,
            "error": None, **fields}


def test_error_answers_raise_typed_exceptions_with_the_problem_code():
    answers = {
        "/v1/jobs/job_1/cancel": _problem(409, "job_finished", "job job_1 has already finished (succeeded)"),
        "/v1/jobs": _problem(422, "validation_error", "body.preset: bad",
                             errors=[{"field": "body.preset", "message": "bad"}]),
        "/v1/datasets": httpx.Response(429, json={"code": "too_many_uploads", "detail": "wait"},
                                       headers={"Retry-After": "3"}),
        "/v1/jobs/job_2": httpx.Response(502, text="<html>Bad Gateway</html>"),
        "/v1/jobs/job_3": httpx.Response(418, text="teapot"),
    }
    drop = _client(lambda request: answers[request.url.path])
    with pytest.raises(Conflict) as conflict:
        drop.cancel_job("job_1")
    assert (conflict.value.status, conflict.value.code) == (409, "job_finished")
    assert str(conflict.value) == "job_finished: job job_1 has already finished (succeeded)"
    with pytest.raises(Unprocessable) as invalid:
        drop.create_job("ds_1", preset="huge")
    assert invalid.value.errors == [{"field": "body.preset", "message": "bad"}]
    with pytest.raises(RateLimited) as limited:
        list(drop.list_datasets())
    assert limited.value.code == "too_many_uploads" and limited.value.retry_after == 3
    with pytest.raises(ServerError) as proxy:  # not problem+json: the status stands in for the code
        drop.get_job("job_2")
    assert proxy.value.code == "http_502" and proxy.value.detail == "Bad Gateway"
    with pytest.raises(ApiError) as other:
        drop.get_job("job_3")
    assert type(other.value) is ApiError and other.value.code == "http_418"


def test_requests_carry_the_token_and_only_the_fields_given():
    seen = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(201, json={"id": "job_1"})

    _client(handler).create_job("ds_1", preset="smoke", overrides={"epochs": 1}, idempotency_key="k")
    assert seen[0].headers["Authorization"] == "Bearer secret" and seen[0].headers["Idempotency-Key"] == "k"
    assert json.loads(seen[0].content) == {"dataset_id": "ds_1", "preset": "smoke", "overrides": {"epochs": 1}}
    _client(handler, token=None).create_job("ds_1")
    assert "Authorization" not in seen[1].headers and json.loads(seen[1].content) == {"dataset_id": "ds_1"}


def test_lists_follow_the_cursor_through_every_page():
    pages = {None: {"data": [{"id": "ds_3"}, {"id": "ds_2"}], "has_more": True, "next_after": "ds_2"},
             "ds_2": {"data": [{"id": "ds_1"}], "has_more": False, "next_after": None}}
    drop = _client(lambda request: httpx.Response(200, json=pages[request.url.params.get("after")]))
    assert [d["id"] for d in drop.list_datasets()] == ["ds_3", "ds_2", "ds_1"]


def _sse(*frames: str) -> httpx.Response:
    return httpx.Response(200, content="".join(frames).encode(), headers={"Content-Type": "text/event-stream"})


def _frame(event_id: int, kind: str) -> str:
    return f"id: {event_id}\nevent: {kind}\ndata: {json.dumps({'id': event_id, 'type': kind})}\n\n"


def test_the_event_stream_ends_with_the_job_and_resumes_after_the_last_event_seen():
    asked = []

    def handler(request: httpx.Request) -> httpx.Response:
        asked.append(request.headers.get("Last-Event-ID"))
        return _sse(_frame(7, "status"), ": keep-alive\n\n", _frame(8, "progress"),
                    'event: end\ndata: {"status": "succeeded"}\n\n', _frame(9, "never read"))

    drop = _client(handler)
    assert [e["id"] for e in drop.stream_events("job_1")] == [7, 8]
    list(drop.stream_events("job_1", last_event_id=6))
    assert asked == [None, "6"]


def test_a_stream_cut_short_names_the_last_event_to_resume_from():
    drop = _client(lambda request: _sse(_frame(7, "status"), _frame(8, "progress")))
    received = []
    with pytest.raises(StreamInterrupted) as cut:
        for event in drop.stream_events("job_1"):
            received.append(event["id"])
    assert received == [7, 8] and cut.value.last_event_id == 8


def test_a_refused_stream_is_a_typed_error():
    drop = _client(lambda request: _problem(429, "too_many_streams", "20 streams open"))
    with pytest.raises(RateLimited) as refused:
        next(drop.stream_events("job_1"))
    assert refused.value.code == "too_many_streams"


def test_an_unreachable_server_is_a_network_error():
    def handler(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused")

    with pytest.raises(NetworkError, match="connection refused"):
        _client(handler).get_job("job_1")
    assert issubclass(NetworkError, DropError)


def test_wait_reports_each_change_and_returns_the_finished_job():
    states = iter([_job("queued"), _job("queued"), _job("running", progress={"phase": "train", "epoch": 1}),
                   _job("succeeded", last_score=1.0, best_score=2.0)])
    seen = []
    done = _client(lambda request: httpx.Response(200, json=next(states))).wait("job_1", poll_s=0,
                                                                                progress=seen.append)
    assert done["status"] == "succeeded" and [j["status"] for j in seen] == ["queued", "running", "succeeded"]


def test_wait_stops_when_its_condition_holds_or_its_time_is_up():
    states = iter([_job("queued"), _job("running")])
    drop = _client(lambda request: httpx.Response(200, json=next(states)))
    assert drop.wait("job_1", until=lambda job: job["status"] == "running", poll_s=0)["status"] == "running"
    drop = _client(lambda request: httpx.Response(200, json=_job("queued")))
    with pytest.raises(WaitTimeout) as late:
        drop.wait("job_1", timeout=0)
    assert late.value.job["status"] == "queued" and isinstance(late.value, TimeoutError)


def test_a_policy_downloads_into_a_folder_under_the_servers_name_for_it(tmp_path):
    def handler(request: httpx.Request) -> httpx.Response:
        assert dict(request.url.params) == {"which": "best", "format": "onnx"}
        return httpx.Response(200, content=b"weights",
                              headers={"Content-Disposition": 'attachment; filename="../../job_1-best-policy.onnx"'})

    drop = _client(handler)
    path = drop.download_policy("job_1", tmp_path, which="best", format="onnx")
    assert path == tmp_path / "job_1-best-policy.onnx" and path.read_bytes() == b"weights"
    assert drop.download_policy("job_1", tmp_path / "mine.onnx", which="best", format="onnx").read_bytes() == b"weights"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["job_1-best-policy.onnx", "mine.onnx"]


def test_a_failed_download_leaves_no_file(tmp_path):
    drop = _client(lambda request: _problem(409, "policy_not_ready", "job job_1 is running"))
    with pytest.raises(Conflict):
        drop.download_policy("job_1", tmp_path / "policy.pt")
    assert not list(tmp_path.iterdir())
