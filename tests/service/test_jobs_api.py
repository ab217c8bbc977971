"""Job requests are validated field by field (422 naming the field), Idempotency-Key replays, and every error is
problem+json."""
from __future__ import annotations

import pytest

PROBLEM = "application/problem+json"


@pytest.fixture(scope="module")
def dataset(client, tokens, hopper_file):
    with open(hopper_file, "rb") as fh:
        r = client.post("/v1/datasets", files={"file": ("h.hdf5", fh)},
                        headers={"Authorization": f"Bearer {tokens['alice']}"})
    return r.json()


@pytest.mark.parametrize("body, field, code", [
    ({"algorithm": "ppo"}, "algorithm", "unknown_algorithm"),
    ({"env": "walker2d"}, "env", "env_mismatch"),
    ({"env": "ant"}, "env", "unknown_env"),
    ({"preset": "huge"}, "preset", "unknown_preset"),
    ({"task": "medium_replay"}, "task", "unknown_task"),  # a typo would otherwise take medium's settings
    ({"overrides": {"dice.nope": 1}}, "dice.nope", "invalid_config"),
    ({"overrides": {"epochs": 0}}, "epochs", "invalid_config"),
    ({"overrides": {"sac.gamma": "high"}}, "sac.gamma", "invalid_config"),
    ({"overrides": {"device": "cuda"}}, "overrides", "invalid_override"),
    ({"overrides": {"dice.lr": 1e-3, "dice": {"lr": 2e-3}}}, "dice.lr", "invalid_config"),  # neither silently wins
    ({"seed": -1}, "seed", "validation_error"),
    ({"colour": "red"}, "colour", "validation_error"),
    ({"algorithm": 5}, "algorithm", "validation_error"),  # not a string at all: a type error, not an unknown name
    ({"algorithm": "ppo", "preset": "huge"}, "preset", "unknown_algorithm"),  # the first bad field's code
    ({"preset": "huge", "seed": -1}, "preset", "validation_error"),  # a field without a code of its own: the usual
])
def test_bad_job_fields_are_422(alice, dataset, body, field, code):
    r = alice.post("/v1/jobs", json={"dataset_id": dataset["id"], "preset": "smoke", **body})
    assert r.status_code == 422, r.text
    assert r.headers["content-type"] == PROBLEM
    problem = r.json()
    assert problem["code"] == code and field in {e["field"] for e in problem["errors"]}, problem


def test_a_body_that_is_not_json_says_so(alice, dataset):
    """Malformed JSON is a 400 that says where it broke, and JSON sent without its Content-Type (curl -d's default) a
    415 naming the header: neither is a 422 about a field named by a character offset."""
    body = f'{{"dataset_id": "{dataset["id"]}", "preset": "smoke",}}'
    r = alice.post("/v1/jobs", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 400 and r.headers["content-type"] == PROBLEM, r.text
    assert r.json()["code"] == "invalid_json" and f"at character {len(body) - 1}" in r.json()["detail"], r.json()
    form = {"Content-Type": "application/x-www-form-urlencoded"}
    r = alice.post("/v1/jobs", content=body.replace(",}", "}"), headers=form)
    assert r.status_code == 415 and r.headers["content-type"] == PROBLEM, r.text
    assert "Content-Type: application/json" in r.json()["detail"]
    r = alice.post("/v1/jobs", json=["not", "an", "object"])  # JSON, of the wrong shape: still a field error
    assert r.status_code == 422 and r.json()["code"] == "validation_error", r.text


def test_a_gymnasium_id_names_its_env(alice, dataset):
    r = alice.post("/v1/jobs", json={"dataset_id": dataset["id"], "preset": "smoke", "env": "Hopper-v4"})
    assert r.status_code == 201 and r.json()["env"] == "hopper", r.text
    alice.post(f"/v1/jobs/{r.json()['id']}/cancel")


def test_unknown_dataset_is_404(alice):
    r = alice.post("/v1/jobs", json={"dataset_id": "ds_missing", "preset": "smoke"})
    assert r.status_code == 404 and r.json()["code"] == "not_found"


def test_idempotency_key(alice, dataset):
    body = {"dataset_id": dataset["id"], "preset": "smoke", "seed": 3}
    key = {"Idempotency-Key": "create-once-1"}
    first = alice.post("/v1/jobs", json=body, headers=key)
    again = alice.post("/v1/jobs", json=body, headers=key)
    assert first.status_code == 201 and again.status_code == 200
    assert first.json()["id"] == again.json()["id"]
    other = alice.post("/v1/jobs", json={**body, "seed": 4}, headers=key)
    assert other.status_code == 422 and other.json()["code"] == "idempotency_key_reused"
    alice.post(f"/v1/jobs/{first.json()['id']}/cancel")


def test_list_filter_and_paging(alice, dataset):
    ids = [alice.post("/v1/jobs", json={"dataset_id": dataset["id"], "preset": "smoke", "seed": 100 + i}).json()["id"]
           for i in range(3)]
    for job_id in ids:
        alice.post(f"/v1/jobs/{job_id}/cancel")
    page = alice.get("/v1/jobs", params={"limit": 2}).json()
    assert page["has_more"] and len(page["data"]) == 2
    rest = alice.get("/v1/jobs", params={"limit": 100, "after": page["next_after"]}).json()
    seen = [j["id"] for j in page["data"] + rest["data"]]
    assert len(seen) == len(set(seen)) and set(ids) <= set(seen)
    assert seen == sorted(seen, reverse=True)
    r = alice.get("/v1/jobs", params={"status": "bogus"})
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM
    assert r.json()["errors"][0]["field"] == "query.status" and "cancelled" in r.json()["detail"], r.text


def test_errors_are_problem_json(client, alice):
    for r in (client.get("/nowhere"), alice.get("/v1/jobs/job_nope"), client.put("/healthz"),
              alice.get("/v1/jobs", params={"limit": 0})):
        assert r.headers["content-type"] == PROBLEM, r.text
        assert {"type", "title", "status", "detail", "code"} <= r.json().keys()


def test_oversized_json_is_413(alice, dataset):
    r = alice.post("/v1/jobs", json={"dataset_id": dataset["id"], "overrides": {"x": "y" * 2_000_000}})
    assert r.status_code == 413 and r.headers["content-type"] == PROBLEM

    def chunks():
        yield b'{"dataset_id": "' + b"x" * 2_000_000 + b'"}'

    r = alice.post("/v1/jobs", content=chunks(), headers={"Content-Type": "application/json"})
    assert r.status_code == 413 and r.headers["content-type"] == PROBLEM


def test_health(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").json() == {"status": "ready"}
    spec = client.get("/openapi.json").json()
    assert "/v1/jobs/{job_id}/policy" in spec["paths"] and "/v1/datasets" in spec["paths"]
    which = next(p for p in spec["paths"]["/v1/jobs/{job_id}/policy"]["get"]["parameters"] if p["name"] == "which")
    assert which["schema"]["enum"] == ["last", "best"] and which["schema"]["default"] == "last"


def test_a_policy_is_awaited_while_the_job_may_succeed_and_not_after(settings):
    """A queued job's policy is not ready yet (worth polling for); a cancelled job's never will be, and its code says
    so. The job sits in a private queue, so it stays queued."""
    from .datasets import tiny_npz
    from .private_api import private_api

    with private_api(settings) as (_, client):
        dataset_id = client.post("/v1/datasets", content=tiny_npz(0)).json()["id"]
        job = client.post("/v1/jobs", json={"dataset_id": dataset_id, "env": "hopper", "preset": "smoke"}).json()
        r = client.get(f"/v1/jobs/{job['id']}/policy")
        assert (r.status_code, r.json()["code"]) == (409, "policy_not_ready"), r.text
        assert client.post(f"/v1/jobs/{job['id']}/cancel").json()["status"] == "cancelled"
        r = client.get(f"/v1/jobs/{job['id']}/policy", params={"which": "best"})
        assert (r.status_code, r.json()["code"]) == (409, "job_not_succeeded"), r.text
        assert client.delete(f"/v1/datasets/{dataset_id}").status_code == 204


def test_a_succeeded_jobs_missing_policy_file_says_which_and_why(settings):
    """An ONNX file the best-effort export could not write is told apart from a file gone from the server; a format
    that is there is served. The job's success is written by hand: nothing trains."""
    from sqlalchemy import update

    from drop_engine.policy_files import FILE_NAMES
    from kernel.models import Job
    from kernel.storage import job_dir

    from .datasets import tiny_npz
    from .private_api import private_api

    with private_api(settings) as (app, client):
        dataset_id = client.post("/v1/datasets", content=tiny_npz(1)).json()["id"]
        job = client.post("/v1/jobs", json={"dataset_id": dataset_id, "env": "hopper", "preset": "smoke"}).json()
        with app.state.sessions.begin() as s:
            s.execute(update(Job).where(Job.id == job["id"]).values(status="succeeded"))
        last = job_dir(app.state.settings, job["id"]) / "policy" / "last"
        last.mkdir(parents=True)
        (last / FILE_NAMES["torchscript"]).write_bytes(b"a policy")
        assert client.get(f"/v1/jobs/{job['id']}/policy").content == b"a policy"
        r = client.get(f"/v1/jobs/{job['id']}/policy", params={"format": "onnx"})
        assert (r.status_code, r.json()["code"]) == (404, "policy_format_unavailable"), r.text
        assert "format=torchscript" in r.json()["detail"]
        r = client.get(f"/v1/jobs/{job['id']}/policy", params={"which": "best"})
        assert (r.status_code, r.json()["code"]) == (404, "policy_file_missing"), r.text
        assert "best policy is no longer on the server" in r.json()["detail"]
        assert client.delete(f"/v1/jobs/{job['id']}").status_code == 204
