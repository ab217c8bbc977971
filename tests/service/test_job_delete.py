"""Deleting a job: refused (409) until it has finished, then its row, its records and its folder go at once; another
owner gets 404, its Idempotency-Key is free again, and /metrics still counts it."""
from __future__ import annotations

import threading
from types import SimpleNamespace

import pytest
from sqlalchemy import func, select

from app.core.auth import hash_token
from drop_engine.config import build_config
from kernel.db import upgrade
from kernel.ids import new_id
from kernel.models import Dataset, DeletedJob, Job, JobCheckpoint, JobEvaluation, JobEvent, JobMetric, Token
from kernel.storage import job_dir
from worker.runner import _add_onnx, run_job

from .private_api import private_api
from .scrapes import sample

# What /metrics counts from the job rows, by name and labels: a deleted job must still count, or they would go down.
COUNTED = {"attempts": ("drop_job_attempts", {}), "waits": ("drop_job_queue_wait_seconds_count", {}),
           "runs": ("drop_job_run_seconds_count", {}), "run_s": ("drop_job_run_seconds_sum", {}),
           "runs_le_inf": ("drop_job_run_seconds_bucket", {"le": "+Inf"}),
           "cache_hits": ("drop_dynamics_cache_lookups_total", {"result": "hit"}),
           "cache_misses": ("drop_dynamics_cache_lookups_total", {"result": "miss"})}


def _counts(client) -> dict[str, float]:
    text = client.get("/metrics").text
    return {key: sample(text, name, **labels) for key, (name, labels) in COUNTED.items()}


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


def test_a_worker_that_lost_a_deleted_job_leaves_no_folder(app, settings, alice, hopper_file):
    """A reaper gave the job up while its worker was still running it (a stale heartbeat: here the row is moved to
    failed by hand), and its owner deleted it: the worker stops at its next step with a checkpoint, as for any lost
    job, and then removes the folder that checkpoint went into."""
    ds = alice.api.upload_dataset(hopper_file)
    sessions = app.state.sessions
    with sessions.begin() as s:
        job = Job(id=new_id("job"), owner_id=s.get(Dataset, ds["id"]).owner_id, dataset_id=ds["id"],
                  algorithm="drop", env="hopper", preset="smoke", overrides={}, seed=0, status="queued",
                  max_attempts=3, max_runtime_s=600, config=build_config(
                      "drop", env="hopper", preset="smoke", overrides={"epochs": 500}).model_dump(mode="json"))
        s.add(job)
    outcome: list[str] = []
    runner = threading.Thread(target=lambda: outcome.append(run_job(settings, sessions, job.id)))
    runner.start()
    alice.api.wait(job.id, until=lambda j: (j["progress"] or {}).get("phase") == "train", timeout=90)
    with sessions.begin() as s:
        s.get(Job, job.id).status = "failed"
    assert alice.delete(f"/v1/jobs/{job.id}").status_code == 204
    runner.join(60)
    assert outcome == ["lost"]
    assert not job_dir(settings, job.id).exists()
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


def _own_sqlite(tmp_path) -> dict:
    url = f"sqlite:///{tmp_path / 'delete.db'}"
    upgrade(url)
    return {"database_url": url}


def _finished_job(app, client) -> Job:
    """A succeeded job of the client's owner, written by hand: nothing trains."""
    token = client.headers["authorization"].split()[1]
    with app.state.sessions.begin() as s:
        owner = s.scalar(select(Token.owner_id).where(Token.token_hash == hash_token(token)))
        job = Job(id=new_id("job"), owner_id=owner, dataset_id=None, algorithm="drop", env="hopper", preset="smoke",
                  overrides={}, seed=0, config={}, status="succeeded", max_attempts=3, max_runtime_s=600,
                  attempts=1, queue_wait_s=3.0, run_s=12.0, dynamics_from_cache=True)
        s.add(job)
    return job


def test_a_deleted_job_still_counts_in_metrics(settings, tmp_path):
    """Over a database of the test's own, so that no other test's job moves the counters between the scrapes."""
    with private_api(settings, **_own_sqlite(tmp_path)) as (app, client):
        job = _finished_job(app, client)
        counted = _counts(client)
        assert counted == {"attempts": 1, "waits": 1, "runs": 1, "run_s": 12.0, "runs_le_inf": 1, "cache_hits": 1,
                           "cache_misses": 0}, counted
        assert sample(client.get("/metrics").text, "drop_jobs", status="succeeded") == 1
        assert client.delete(f"/v1/jobs/{job.id}").status_code == 204
        assert _counts(client) == counted, "the deleted job still counts"
        assert sample(client.get("/metrics").text, "drop_jobs", status="succeeded") == 0


def test_a_failed_onnx_export_warns_only_the_attempt_that_owns_the_job(app, alice, hopper_file, tmp_path):
    """The warning goes in only while the job is still this attempt's: not into a job taken by another attempt, and
    into a deleted job not at all (its row is gone: an unfenced insert broke on the foreign key)."""
    ds = alice.api.upload_dataset(hopper_file)
    sessions = app.state.sessions
    with sessions.begin() as s:
        job = Job(id=new_id("job"), owner_id=s.get(Dataset, ds["id"]).owner_id, dataset_id=ds["id"],
                  algorithm="drop", env="hopper", preset="smoke", overrides={}, seed=0, status="running",
                  max_attempts=3, max_runtime_s=600, attempts=2, config={})
        s.add(job)
    unexportable = SimpleNamespace(policy={"last": {"torchscript": str(tmp_path / "missing.pt")}})

    def warnings() -> int:
        with sessions() as s:
            return s.scalar(select(func.count()).where(JobEvent.job_id == job.id, JobEvent.type == "warning"))

    _add_onnx(sessions, job.id, 1, unexportable, obs_dim=11)
    assert warnings() == 0, "attempt 1 no longer owns the job"
    _add_onnx(sessions, job.id, 2, unexportable, obs_dim=11)
    assert warnings() == 1
    with sessions.begin() as s:
        s.delete(s.get(Job, job.id))
    _add_onnx(sessions, job.id, 2, unexportable, obs_dim=11)
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_the_records_go_with_the_job_on_either_backend(settings, tmp_path, backend):
    """The foreign keys' cascade takes a job's records on SQLite (`drop serve`) as on PostgreSQL."""
    with private_api(settings, **(_own_sqlite(tmp_path) if backend == "sqlite" else {})) as (app, client):
        sessions = app.state.sessions
        job = _finished_job(app, client)
        with sessions.begin() as s:
            s.add_all([JobEvent(job_id=job.id, type="status", message="succeeded"),
                       JobMetric(job_id=job.id, step=1, name="sac/q_mean", value=1.0),
                       JobEvaluation(job_id=job.id, epoch=1, mean_return=1.0, normalized_score=1.0),
                       JobCheckpoint(job_id=job.id, epoch=1, step=1, path="jobs/x/c.pt", size_bytes=1)])
        assert set(_records(sessions, job.id).values()) == {1}
        assert client.delete(f"/v1/jobs/{job.id}").status_code == 204
        assert set(_records(sessions, job.id).values()) == {0}
        with sessions() as s:
            assert s.get(DeletedJob, job.id).run_s == 12.0
