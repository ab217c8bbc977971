"""Cancellation of a queued and of a running job (the running one stops at its next step with a final checkpoint),
cancelling twice (the same answer, no second transition), cancelling a finished job (409), and the dataset that
cannot be deleted while a job uses it; a cancel in the middle of a long dynamics epoch."""
from __future__ import annotations

import time

import numpy as np

from drop_engine.collect import read_arrays
from drop_engine.data import save_hdf5


def test_cancel_running_and_queued(alice, worker, hopper_file):
    ds = alice.api.upload_dataset(hopper_file)
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
    # Training has begun, so the job already names the ensemble it trains on.
    assert job["dynamics"]["cache_key"] and job["dynamics"]["from_cache"] in (True, False)

    # The single worker is busy, so the second job is still queued: it is cancelled at once, which is a 200 (nothing
    # to wait for), as is asking again.
    r = alice.post(f"/v1/jobs/{queued['id']}/cancel")
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    again = alice.post(f"/v1/jobs/{queued['id']}/cancel")
    assert again.status_code == 200 and again.json()["status"] == "cancelled"
    assert again.json()["finished_at"] == r.json()["finished_at"]

    r = alice.delete(f"/v1/datasets/{ds['id']}")
    assert r.status_code == 409 and r.json()["code"] == "dataset_in_use"

    r = alice.post(f"/v1/jobs/{running['id']}/cancel")
    assert (r.status_code, r.json()["status"]) in ((202, "cancelling"), (200, "cancelled")), r.json()
    again = alice.post(f"/v1/jobs/{running['id']}/cancel")
    assert (again.status_code, again.json()["status"]) in ((202, "cancelling"), (200, "cancelled")), again.json()
    done = alice.api.wait(running["id"], timeout=60)  # its next step is ms away; the niced pool may wait for CPU
    assert done["status"] == "cancelled", done
    assert done["progress"]["epoch"] < 500 and done["dynamics"] == job["dynamics"]
    assert alice.post(f"/v1/jobs/{running['id']}/cancel").status_code == 200

    events = alice.get(f"/v1/jobs/{running['id']}/events", params={"limit": 1000}).json()["data"]
    requested = [i for i, e in enumerate(events) if e["message"] == "cancellation requested"]
    assert len(requested) == 1, "a second cancel is not a second transition"
    assert events[-1]["message"] == "cancelled at a step boundary; final checkpoint written"
    # The final checkpoint: written after the request, where the run stopped, and the newest one listed.
    last = [e["data"] for e in events[requested[0]:] if e["type"] == "checkpoint"][-1]
    ckpts = alice.get(f"/v1/jobs/{running['id']}/checkpoints").json()["data"]
    assert max((c["epoch"], c["step"]) for c in ckpts) == (last["epoch"], last["step"])
    assert last["epoch"] == done["progress"]["epoch"]
    r = alice.get(f"/v1/jobs/{running['id']}/policy")
    assert r.status_code == 409 and r.headers["content-type"] == "application/problem+json"
    assert r.json()["code"] == "job_not_succeeded", "a cancelled job will never have a policy: not worth waiting on"

    # The cancelled queued job is never run: its message reaches the worker, which cannot claim it.
    time.sleep(2)
    job = alice.get(f"/v1/jobs/{queued['id']}").json()
    assert job["status"] == "cancelled" and job["attempts"] == 0 and job["started_at"] is None
    assert job["dynamics"] is None
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


def test_cancel_inside_a_dynamics_epoch(alice, worker, hopper_file, tmp_path):
    """An epoch of this fit takes tens of seconds, yet the cancel lands inside the first one (its progress never
    reaches epoch 1, on however loaded a machine), and the job does not claim a checkpoint: none was written."""
    arrays, attrs = read_arrays(hopper_file)
    path = tmp_path / "hopper-x7.hdf5"
    core = {k: v for k, v in arrays.items() if not k.startswith("infos/")}  # under the upload limit
    save_hdf5(path, {k: np.concatenate([v] * 7) for k, v in core.items()}, attrs)  # 14,000 rows
    ds = alice.api.upload_dataset(path)
    dynamics = {"members": 7, "elites": 5, "hidden": 800, "layers": 4, "batch_size": 256, "max_epochs": 1000,
                "patience": 1000}
    job = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke", "overrides": {"dynamics": dynamics}})
    assert job.status_code == 201, job.json()
    job = alice.api.wait(job.json()["id"], until=lambda j: j["status"] == "running", timeout=60)
    time.sleep(3)  # into the first epoch: its engine is imported and its data loaded by now

    asked = time.monotonic()
    assert alice.post(f"/v1/jobs/{job['id']}/cancel").status_code == 202
    done = alice.api.wait(job["id"], timeout=60)
    took = time.monotonic() - asked
    assert done["status"] == "cancelled", (took, done)
    assert (done["progress"] or {}).get("step", 0) == 0, "stopped inside the first epoch"
    events = alice.get(f"/v1/jobs/{job['id']}/events", params={"limit": 1000}).json()["data"]
    assert events[-1]["message"] == "cancelled before its first checkpoint; nothing to resume was written"
    assert done["dynamics"] is None, "a half-fitted ensemble is not the job's"
    assert not any(e["type"] == "checkpoint" for e in events)
    assert alice.get(f"/v1/jobs/{job['id']}/checkpoints").json()["data"] == []
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


def test_attempt_past_max_runtime_fails_with_timeout(alice, worker, hopper_file):
    ds = alice.api.upload_dataset(hopper_file)
    job = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke", "max_runtime_s": 8,
                                       "overrides": {"epochs": 500}}).json()
    done = alice.api.wait(job["id"], timeout=90)
    assert done["status"] == "failed" and done["error"]["code"] == "timeout", done
    assert "max_runtime_s=8" in done["error"]["message"]
    _assert_cannot_cancel(alice, done)
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


def test_cancel_succeeded_job_is_409(alice, worker, hopper_file):
    ds = alice.api.upload_dataset(hopper_file)
    job = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke"}).json()
    done = alice.api.wait(job["id"], timeout=90)
    assert done["status"] == "succeeded", done
    _assert_cannot_cancel(alice, done)
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


def _assert_cannot_cancel(alice, done: dict) -> None:
    r = alice.post(f"/v1/jobs/{done['id']}/cancel")
    assert r.status_code == 409 and r.headers["content-type"] == "application/problem+json"
    assert r.json()["code"] == "job_finished" and done["status"] in r.json()["detail"]
    after = alice.get(f"/v1/jobs/{done['id']}").json()
    assert (after["status"], after["finished_at"]) == (done["status"], done["finished_at"])
