"""Cancellation of a queued and of a running job, and the dataset that cannot be deleted while a job uses it."""
from __future__ import annotations

import time


def test_cancel_running_and_queued(alice, worker, hopper_file):
    ds = alice.upload(hopper_file).json()
    long = {"dataset_id": ds["id"], "preset": "smoke", "overrides": {"epochs": 500}}
    running = alice.post("/v1/jobs", json=long).json()
    queued = alice.post("/v1/jobs", json={**long, "seed": 7}).json()

    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        job = alice.get(f"/v1/jobs/{running['id']}").json()
        if job["status"] == "running" and (job["progress"] or {}).get("phase") == "train":
            break
        time.sleep(0.2)
    assert job["status"] == "running", job

    # The single worker is busy, so the second job is still queued: it is cancelled at once.
    r = alice.post(f"/v1/jobs/{queued['id']}/cancel")
    assert r.status_code == 202 and r.json()["status"] == "cancelled"
    assert alice.post(f"/v1/jobs/{queued['id']}/cancel").status_code == 409

    r = alice.delete(f"/v1/datasets/{ds['id']}")
    assert r.status_code == 409 and r.json()["code"] == "dataset_in_use"

    r = alice.post(f"/v1/jobs/{running['id']}/cancel")
    assert r.status_code == 202 and r.json()["status"] in ("cancelling", "cancelled")
    done = alice.wait(running["id"], {"cancelled", "succeeded", "failed"}, timeout=60)
    assert done["status"] == "cancelled", done
    assert done["progress"]["epoch"] < 500
    ckpts = alice.get(f"/v1/jobs/{running['id']}/checkpoints").json()["data"]
    assert ckpts, "a cancelled run writes a final checkpoint"
    r = alice.get(f"/v1/jobs/{running['id']}/policy")
    assert r.status_code == 409 and r.headers["content-type"] == "application/problem+json"

    # The cancelled queued job is never run: its message reaches the worker, which cannot claim it.
    time.sleep(2)
    job = alice.get(f"/v1/jobs/{queued['id']}").json()
    assert job["status"] == "cancelled" and job["attempts"] == 0 and job["started_at"] is None
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


def test_attempt_past_max_runtime_fails_with_timeout(alice, worker, hopper_file):
    ds = alice.upload(hopper_file).json()
    job = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke", "max_runtime_s": 8,
                                       "overrides": {"epochs": 500}}).json()
    done = alice.wait(job["id"], {"succeeded", "failed", "cancelled"}, timeout=90)
    assert done["status"] == "failed" and done["error"]["code"] == "timeout", done
    assert "max_runtime_s=8" in done["error"]["message"]
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204
