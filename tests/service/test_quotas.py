"""Per-owner quotas against the real service: unfinished jobs beyond the quota get 429, uploads that would take an
owner's stored bytes beyond theirs get 413 and leave nothing behind, and simultaneous requests cannot slip past."""
from __future__ import annotations

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from sqlalchemy import text

from app.owners.lock import lock_owner
from kernel.models import Job

from .datasets import tiny_npz
from .private_api import private_api

PROBLEM = "application/problem+json"
JOB_QUOTA = 2


@pytest.fixture(scope="module")
def tight(settings, hopper_file):
    """The API with small quotas for a fresh owner; one hopper dataset fits in the storage quota, two do not."""
    with private_api(settings, max_active_jobs_per_owner=JOB_QUOTA,
                     max_stored_bytes_per_owner=hopper_file.stat().st_size * 3 // 2) as api:
        yield api


@pytest.fixture
def client(tight):
    return tight[1]


def _concurrently(app, *requests: tuple[str, str, dict]) -> list[httpx.Response]:
    """Send the requests at once: the app's sync handlers run on parallel threads, each with its own connection."""
    async def run():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as c:
            return await asyncio.gather(*(c.request(method, url, **kw) for method, url, kw in requests))

    return asyncio.run(run())


def _assert_problem(r, status: int, code: str, *needles: str) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM
    body = r.json()
    assert body["code"] == code and body["status"] == status, body
    for needle in needles:
        assert needle in body["detail"], body
    return body


def _upload(client, path: Path):
    with open(path, "rb") as fh:
        return client.post("/v1/datasets", files={"file": (path.name, fh, "application/x-hdf5")})


@pytest.fixture
def datasets(client):
    """More datasets than the job quota: creates on different datasets do not wait on each other's dataset lock."""
    ids = []
    for seed in range(JOB_QUOTA + 2):
        r = client.post("/v1/datasets", content=tiny_npz(seed))
        assert r.status_code == 201, r.text
        ids.append(r.json()["id"])
    yield ids
    for job in client.get("/v1/jobs", params={"limit": 100}).json()["data"]:
        client.post(f"/v1/jobs/{job['id']}/cancel")
    for dataset_id in ids:
        assert client.delete(f"/v1/datasets/{dataset_id}").status_code == 204


def _active(client) -> list[str]:
    return [j["id"] for j in client.get("/v1/jobs", params={"limit": 100}).json()["data"]
            if j["status"] in ("queued", "running", "cancelling")]


def _job(dataset_id: str, seed: int = 0) -> dict:
    return {"dataset_id": dataset_id, "env": "hopper", "preset": "smoke", "seed": seed}


def test_jobs_beyond_the_quota_are_429(client, datasets):
    first = client.post("/v1/jobs", json=_job(datasets[0]), headers={"Idempotency-Key": "quota-1"})
    assert first.status_code == 201
    assert client.post("/v1/jobs", json=_job(datasets[1])).status_code == 201

    r = client.post("/v1/jobs", json=_job(datasets[2]))
    _assert_problem(r, 429, "job_quota_exceeded", f"{JOB_QUOTA} unfinished jobs", "DROP_MAX_ACTIVE_JOBS_PER_OWNER")
    assert r.headers["retry-after"].isdigit()
    assert len(_active(client)) == JOB_QUOTA
    # A replay of a job that exists is not a new job, and a bad request still hears what is wrong with it first.
    again = client.post("/v1/jobs", json=_job(datasets[0]), headers={"Idempotency-Key": "quota-1"})
    assert again.status_code == 200 and again.json()["id"] == first.json()["id"]
    _assert_problem(client.post("/v1/jobs", json={**_job(datasets[2]), "preset": "huge"}), 422, "unknown_preset")

    client.post(f"/v1/jobs/{first.json()['id']}/cancel")  # a finished job frees its place
    assert client.post("/v1/jobs", json=_job(datasets[2])).status_code == 201


def test_simultaneous_creates_do_not_slip_past(tight, client, datasets):
    auth = {"Authorization": client.headers["authorization"]}
    requests = [("POST", "/v1/jobs", {"json": _job(dataset_id), "headers": auth}) for dataset_id in datasets]
    codes = sorted(r.status_code for r in _concurrently(tight[0], *requests))
    assert codes == [201] * JOB_QUOTA + [429] * (len(datasets) - JOB_QUOTA)
    assert len(_active(client)) == JOB_QUOTA


def test_a_replay_that_waited_on_the_owner_lock_is_a_replay(tight, client, datasets):
    """Two creates with one Idempotency-Key and one place left both find no job under the key, then wait on the owner's
    lock (held here until both wait): the one served second gets the first's job, not a 429 for the quota that job
    took."""
    app = tight[0]
    held = client.post("/v1/jobs", json=_job(datasets[0]))
    assert held.status_code == 201
    auth = {"Authorization": client.headers["authorization"], "Idempotency-Key": "wait-on-the-lock"}
    request = ("POST", "/v1/jobs", {"json": _job(datasets[1]), "headers": auth})
    def waiting() -> int:  # in a transaction of its own: within one, pg_stat_activity is one snapshot
        with app.state.engine.connect() as c:
            return c.execute(text("SELECT count(*) FROM pg_stat_activity WHERE wait_event_type = 'Lock' "
                                  "AND query LIKE 'UPDATE owners%'")).scalar()

    with app.state.sessions() as s, ThreadPoolExecutor(1) as pool:
        lock_owner(s, s.get(Job, held.json()["id"]).owner_id)
        try:
            sent = pool.submit(_concurrently, app, request, request)
            deadline = time.monotonic() + 30
            while waiting() < 2 and not sent.done():
                assert time.monotonic() < deadline, "the creates never waited on the owner's lock"
                time.sleep(0.02)
        finally:
            s.rollback()  # the lock: the creates go on
        responses = sorted(sent.result(), key=lambda r: r.status_code)
    assert [r.status_code for r in responses] == [200, 201], [r.text for r in responses]
    assert responses[0].json()["id"] == responses[1].json()["id"]


def _leftovers(settings) -> set[Path]:
    return {p for sub in ("uploads", "datasets") for p in (settings.data_dir / sub).iterdir()}


def test_uploads_beyond_the_storage_quota_are_413(client, settings, hopper_file):
    first = _upload(client, hopper_file)
    assert first.status_code == 201, first.text
    before = _leftovers(settings)
    data = hopper_file.read_bytes()
    needles = ("DROP_MAX_STORED_BYTES_PER_OWNER", f"take {len(data)} of the")
    # Content-Length known: refused before the body is read, raw or multipart.
    _assert_problem(client.post("/v1/datasets", content=data), 413, "storage_quota_exceeded", *needles)
    _assert_problem(_upload(client, hopper_file), 413, "storage_quota_exceeded", *needles)

    def chunks():  # no Content-Length: refused while streaming
        for i in range(0, len(data), 65536):
            yield data[i:i + 65536]

    _assert_problem(client.post("/v1/datasets", content=chunks()), 413, "storage_quota_exceeded", *needles)
    assert _leftovers(settings) == before
    assert [d["id"] for d in client.get("/v1/datasets").json()["data"]] == [first.json()["id"]]
    # What still fits is not refused by the quota (this one is cut short, so the validator refuses it instead).
    _assert_problem(client.post("/v1/datasets", content=data[: len(data) // 4]), 422, "invalid_dataset")
    assert client.delete(f"/v1/datasets/{first.json()['id']}").status_code == 204


def test_simultaneous_uploads_are_recounted_before_saving(tight, client, settings, hopper_file):
    """Each upload fits alone, so both stream and validate; only one may be saved, and the other leaves nothing."""
    before = _leftovers(settings)
    token = client.headers["authorization"]
    data = hopper_file.read_bytes()
    request = ("POST", "/v1/datasets", {"content": data, "headers": {"Authorization": token}})
    responses = sorted(_concurrently(tight[0], request, request), key=lambda r: r.status_code)
    assert [r.status_code for r in responses] == [201, 413]
    _assert_problem(responses[1], 413, "storage_quota_exceeded", f"this {len(data)}-byte dataset does not fit")
    assert client.delete(f"/v1/datasets/{responses[0].json()['id']}").status_code == 204
    assert _leftovers(settings) == before
