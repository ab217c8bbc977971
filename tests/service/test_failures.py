"""A failing job records error {code, message} on the job and the traceback in its events, never in a response; a
diverging run fails with `training_diverged`, and a database error's message never shows its SQL."""
from __future__ import annotations

from pathlib import Path

from drop_engine.config import build_config
from kernel.ids import new_id
from kernel.models import Dataset, Job
from worker.runner import run_job

# The temperature runs away (tests/test_divergence.py): the critic's loss overflows by the first epoch's end.
RUNAWAY_ALPHA = {"sac": {"alpha_lr": 1.0, "target_entropy": 1000.0}, "epochs": 3, "steps_per_epoch": 50}


def test_failed_job_keeps_traceback_out_of_the_api(app, settings, alice, hopper_file, tmp_path):
    ds = alice.api.upload_dataset(hopper_file)
    sessions = app.state.sessions
    with sessions() as s:
        owner_id = s.get(Dataset, ds["id"]).owner_id
    # A job on a file that vanished from storage (for example a volume that was not mounted), run by the worker code
    # in this process so the test does not race the real worker for the message.
    with sessions.begin() as s:
        s.get(Dataset, ds["id"]).path = str(tmp_path / "gone.hdf5")
        job = Job(id=new_id("job"), owner_id=owner_id, dataset_id=ds["id"], algorithm="drop", env="hopper",
                  preset="smoke", overrides={}, seed=0, config={"preset": "smoke"}, status="queued", max_attempts=3,
                  max_runtime_s=600)
        s.add(job)
    assert run_job(settings, sessions, job.id) == "failed"
    got = alice.get(f"/v1/jobs/{job.id}").json()
    assert got["status"] == "failed" and got["error"]["code"] == "invalid_dataset"
    assert "deleted" in got["error"]["message"] and "Traceback" not in str(got)
    events = alice.get(f"/v1/jobs/{job.id}/events").json()["data"]
    assert [e["type"] for e in events][-2:] == ["status", "traceback"]
    assert events[-1]["message"].startswith("Traceback")
    assert run_job(settings, sessions, job.id) == "skipped"  # a redelivered message does nothing
    assert not Path(tmp_path / "gone.hdf5").exists()


def test_diverging_job_fails_with_training_diverged(alice, worker, hopper_file):
    ds = alice.api.upload_dataset(hopper_file)
    job = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke", "overrides": RUNAWAY_ALPHA}).json()
    done = alice.api.wait(job["id"], timeout=90)
    assert done["status"] == "failed" and done["error"]["code"] == "training_diverged", done
    assert done["error"]["message"].startswith("training diverged: sac/") and "at step 50" in done["error"]["message"]
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


def test_database_error_message_shows_no_sql(app, settings, alice, hopper_file, monkeypatch):
    """With divergence detection off, the diverged metrics reach PostgreSQL, which refuses Infinity in JSON: the job
    fails with the error's type alone, and the statement is only in its traceback event."""
    monkeypatch.setattr("drop_engine.trainer.check_finite", lambda metrics, step: None)
    ds = alice.api.upload_dataset(hopper_file)
    sessions = app.state.sessions
    with sessions.begin() as s:
        dataset = s.get(Dataset, ds["id"])
        job = Job(id=new_id("job"), owner_id=dataset.owner_id, dataset_id=ds["id"], algorithm="drop", env="hopper",
                  preset="smoke", overrides=RUNAWAY_ALPHA, seed=0, status="queued", max_attempts=3, max_runtime_s=600,
                  config=build_config("drop", env="hopper", preset="smoke",
                                      overrides=RUNAWAY_ALPHA).model_dump(mode="json"))
        s.add(job)
    assert run_job(settings, sessions, job.id) == "failed"  # in this process, so the check can be switched off
    got = alice.get(f"/v1/jobs/{job.id}").json()
    assert got["error"] == {"code": "internal_error", "message": "the run stopped on a database error (DataError); "
                                                                "the details are in the job's traceback event"}
    trace = alice.get(f"/v1/jobs/{job.id}/events").json()["data"][-1]
    assert trace["type"] == "traceback" and "[SQL: " in trace["message"]  # SQLAlchemy's statement, for the owner
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204
