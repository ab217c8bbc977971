"""Schemathesis against the app's own OpenAPI schema, in-process over the test's real PostgreSQL and Redis: no 500s,
invalid requests are refused with a 4xx, every error is problem+json, and every response conforms to the schema.

Job creation is fuzzed too: job bodies point at a tiny dataset of the fuzzing owner with preset smoke, on a private
queue that no worker reads, and every job it made is cancelled afterwards, so nothing trains.
"""
from __future__ import annotations

import hypothesis
import pytest
import schemathesis
from hypothesis import HealthCheck
from hypothesis import strategies as st
from schemathesis.checks import (
    content_type_conformance,
    negative_data_rejection,
    not_a_server_error,
    response_schema_conformance,
    status_code_conformance,
)
from schemathesis.generation import GenerationMode

from .datasets import tiny_npz
from .private_api import private_api

EXAMPLES_PER_OPERATION = 15
CHECKS = [not_a_server_error, negative_data_rejection, status_code_conformance, content_type_conformance,
          response_schema_conformance]
PROBLEM = "application/problem+json"


@pytest.fixture
def fuzzed(settings):
    """A fresh owner's API on a private queue, its token, and that owner's tiny dataset and a queued job on it."""
    with private_api(settings) as (app, client):
        r = client.post("/v1/datasets", content=tiny_npz(0))
        assert r.status_code == 201, r.text
        dataset_id = r.json()["id"]
        r = client.post("/v1/jobs", json={"dataset_id": dataset_id, "env": "hopper", "preset": "smoke"})
        assert r.status_code == 201, r.text
        yield app, {"Authorization": client.headers["authorization"]}, {"dataset_id": dataset_id,
                                                                       "job_id": r.json()["id"]}


def _tame(case, dataset_id: str) -> None:
    """A valid job body gets the real tiny dataset and the smoke preset. Invalid ones are left as generated: filling in
    their dataset could repair exactly what made them invalid (a missing or mistyped dataset_id)."""
    negative = case.meta is not None and case.meta.generation.mode.is_negative
    if case.method == "POST" and case.path == "/v1/jobs" and isinstance(case.body, dict) and not negative:
        case.body["dataset_id"] = dataset_id
        case.body["preset"] = "smoke"


def _cases(operation, known: dict[str, str]):
    """Valid and invalid requests, plus valid ones on the owner's real objects (random ids only ever find 404)."""
    strategies = [operation.as_strategy(mode) for mode in GenerationMode]
    real = {name: value for name, value in known.items() if f"{{{name}}}" in operation.path}
    if real:
        strategies.append(operation.as_strategy(GenerationMode.POSITIVE, path_parameters=real))
    return st.one_of(*strategies)


def test_api_conforms_to_its_schema(fuzzed, capsys):
    app, auth, known = fuzzed
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    cases = 0

    def check(case) -> None:
        nonlocal cases
        _tame(case, known["dataset_id"])
        response = case.call(headers=dict(auth))  # a copy: the call adds its own headers to the dict it gets
        cases += 1
        case.validate_response(response, checks=CHECKS, headers=auth)
        if response.status_code >= 400:
            assert response.headers["content-type"] == [PROBLEM], (case.as_curl_command(), response.text)
            body = response.json()
            assert body["status"] == response.status_code and body["code"] and body["detail"], body

    operations = [result.ok() for result in schema.get_all_operations()]
    # derandomize: CI sees the same cases on every run, so a red build is reproducible and never a coin toss
    settings = hypothesis.settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, database=None,
                                   derandomize=True, suppress_health_check=list(HealthCheck))
    for operation in operations:
        settings(hypothesis.given(_cases(operation, known))(check))()
    with capsys.disabled():
        print(f"\nschemathesis: {cases} cases over {len(operations)} operations")
    assert len(operations) >= 16 and cases >= len(operations)


def test_what_fuzzing_found_is_a_4xx(alice):
    """Each once answered 500: a cursor past the (now 64-bit) id columns or holding a NUL, a metric name with a NUL, and
    a second job with an empty Idempotency-Key (the request is checked before any lookup, so these ids need not
    exist). A cursor past 32 bits is a cursor (migration 0006): the missing job is what is wrong."""
    for path in ("/v1/jobs/job_missing/events", "/v1/jobs/job_missing/metrics"):
        assert alice.get(path, params={"after": 2**31}).status_code == 404
    for path, params in (("/v1/jobs/job_missing/events", {"after": 2**63}),
                         ("/v1/jobs/job_missing/metrics", {"after": 2**63}),
                         ("/v1/jobs/job_missing/metrics", {"name": "loss\x00"}),
                         ("/v1/jobs", {"after": "\x00"}), ("/v1/datasets", {"after": "ds_\x00"})):
        r = alice.get(path, params=params)
        assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, r.text
        assert r.json()["errors"][0]["field"] == f"query.{next(iter(params))}"
    r = alice.post("/v1/jobs", json={"dataset_id": "ds_missing"}, headers={"Idempotency-Key": ""})
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "header.idempotency-key", r.text


def test_an_unusable_last_event_id_streams_from_the_start(fuzzed):
    from fastapi.testclient import TestClient

    app, auth, known = fuzzed
    with TestClient(app, headers=auth) as client:
        cancelled = client.post(f"/v1/jobs/{known['job_id']}/cancel").json()
        assert cancelled["status"] == "cancelled"  # the stream ends at once
        for last in (b"9" * 20, "²".encode("latin-1")):  # past 64 bits, and not a number
            with client.stream("GET", f"/v1/jobs/{known['job_id']}/events",
                               headers={"Accept": "text/event-stream", "Last-Event-ID": last}) as r:
                text = "".join(r.iter_text())
            assert r.status_code == 200 and "event: status" in text and "event: end" in text, text


def test_every_json_success_names_its_fields(fuzzed):
    """A success answered as a bare "object" would let the fuzz test's response check pass on anything."""
    app, _, _ = fuzzed
    spec = app.openapi()
    untyped = []
    for path, methods in spec["paths"].items():
        for method, op in methods.items():
            for code, response in op["responses"].items():
                schema = response.get("content", {}).get("application/json", {}).get("schema")
                if code.startswith("2") and schema is not None and "$ref" not in schema:
                    untyped.append(f"{method.upper()} {path} {code}: {schema}")
    assert not untyped, untyped
    job = spec["components"]["schemas"]["JobOut"]
    assert {"status", "progress", "best_score", "error"} <= set(job["required"])
