"""Deleting a job: refused (409) until it has finished, then its row, its records and its folder go at once; another
owner gets 404, and its Idempotency-Key is free again."""
from __future__ import annotations

from sqlalchemy import func, select

from kernel.models import JobCheckpoint, JobEvaluation, JobEvent, JobMetric
from kernel.storage import job_dir


def _records(sessions, job_id: str) -> dict[str, int]:
    with sessions() as s:
        return {m.__tablename__: s.scalar(select(func.count()).select_from(m).where(m.job_id == job_id))
                for m in (JobEvent, JobMetric, JobEvaluation, JobCheckpoint)}


def test_a_job_is_deleted_once_finished_with_its_records_and_files(app, settings, alice, bob, worker, hopper_file):
    ds = alice.api.upload_dataset(hopper_file)
    key = {"Idempotency-Key": "delete-me"}
    long = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke", "overrides": {"epochs": 500}},
                      headers=key).json()
    alice.api.wait(long["id"], until=lambda j: (j["progress"] or {}).get("phase") == "train", timeout=90)
    folder = job_dir(settings, long["id"])
    assert folder.is_dir()

    r = alice.delete(f"/v1/jobs/{long['id']}")
    assert r.status_code == 409 and r.json()["code"] == "job_not_finished", r.json()
    assert "cancel it" in r.json()["detail"]
    assert alice.get(f"/v1/jobs/{long['id']}").status_code == 200 and folder.is_dir()

    alice.post(f"/v1/jobs/{long['id']}/cancel")
    assert alice.api.wait(long["id"], timeout=60)["status"] == "cancelled"
    records = _records(app.state.sessions, long["id"])
    assert records["job_events"] and records["job_metrics"] and records["job_checkpoints"], records
    assert bob.delete(f"/v1/jobs/{long['id']}").status_code == 404
    assert folder.is_dir(), "another owner's delete touches nothing"

    assert alice.delete(f"/v1/jobs/{long['id']}").status_code == 204
    assert alice.get(f"/v1/jobs/{long['id']}").status_code == 404
    assert long["id"] not in {j["id"] for j in alice.get("/v1/jobs", params={"limit": 100}).json()["data"]}
    assert not folder.exists()
    assert set(_records(app.state.sessions, long["id"]).values()) == {0}
    assert alice.delete(f"/v1/jobs/{long['id']}").status_code == 404

    # The key named a job that is gone, so it makes a new one; this one succeeds, and goes with its policies.
    short = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke"}, headers=key)
    assert short.status_code == 201 and short.json()["id"] != long["id"]
    done = alice.api.wait(short.json()["id"], timeout=120)
    assert done["status"] == "succeeded", done
    assert alice.get(f"/v1/jobs/{done['id']}/policy").status_code == 200
    assert alice.delete(f"/v1/jobs/{done['id']}").status_code == 204
    assert alice.get(f"/v1/jobs/{done['id']}/policy").status_code == 404
    assert not job_dir(settings, done["id"]).exists()
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204
