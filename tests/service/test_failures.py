"""A failing job records error {code, message} on the job and the traceback in its events, never in a response."""
from __future__ import annotations

from pathlib import Path

from app.ids import new_id
from app.models import Dataset, Job
from worker.runner import run_job


def test_failed_job_keeps_traceback_out_of_the_api(app, settings, alice, hopper_file, tmp_path):
    ds = alice.upload(hopper_file).json()
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
