"""A failing job records error {code, message} on the job and the traceback in its events, never in a response; a
diverging run fails with `training_diverged`, and a database error's message never shows its SQL."""
from __future__ import annotations

import psycopg
import pytest
from sqlalchemy import event, select, text
from sqlalchemy.exc import OperationalError

from drop_engine.config import build_config
from kernel.ids import new_id
from kernel.job_state import JobStatus
from kernel.models import Dataset, Job, JobEvent
from worker import runner
from worker.runner import run_job

# The temperature runs away (tests/engine/test_divergence.py): the critic's loss overflows by the first epoch's end.
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
    assert got["attempts"] == 1
    # A redelivered message does nothing: no second attempt, no new event, the error and timestamps as they were.
    assert run_job(settings, sessions, job.id) == "skipped"
    assert alice.get(f"/v1/jobs/{job.id}").json() == got
    assert alice.get(f"/v1/jobs/{job.id}/events").json()["data"] == events


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


@pytest.mark.parametrize("lost", ["before", "after"])
def test_a_lost_connection_does_not_cost_a_finished_run_its_attempt(app, settings, alice, hopper_file, monkeypatch,
                                                                     lost):
    """The database connection goes as the worker records a finished run: the server ends it before the write, or
    the write commits and its answer is lost. The record is tried again, and the job succeeds on its first attempt
    with one status event for it."""
    ds = alice.api.upload_dataset(hopper_file)
    sessions = app.state.sessions
    with sessions.begin() as s:
        dataset = s.get(Dataset, ds["id"])
        job = Job(id=new_id("job"), owner_id=dataset.owner_id, dataset_id=ds["id"], algorithm="mopo", env="hopper",
                  preset="smoke", overrides={}, seed=0, status="queued", max_attempts=3, max_runtime_s=600,
                  config=build_config("mopo", env="hopper", preset="smoke", overrides={"epochs": 1}).model_dump(
                      mode="json"))
        s.add(job)
    real, dropped = runner.transition, []

    def dropping(s, job_id, to, **kwargs):
        if to is JobStatus.SUCCEEDED and not dropped:
            dropped.append(lost)
            if lost == "before":  # the server ends this session's connection: the statement fails, nothing commits
                s.execute(text("SELECT pg_terminate_backend(pg_backend_pid())"))
            event.listen(s, "after_commit", _answer_lost, once=True)
        return real(s, job_id, to, **kwargs)

    monkeypatch.setattr(runner, "FINISH_RETRY_S", (0.1,))
    monkeypatch.setattr(runner, "transition", dropping)
    assert run_job(settings, sessions, job.id) == "succeeded" and dropped == [lost]
    got = alice.get(f"/v1/jobs/{job.id}").json()
    assert got["status"] == "succeeded" and got["attempts"] == 1 and got["error"] is None
    events = alice.get(f"/v1/jobs/{job.id}/events", params={"limit": 1000}).json()["data"]
    assert [e["data"]["status"] for e in events if e["type"] == "status"] == ["running", "succeeded"]
    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204


def _answer_lost(session) -> None:
    raise OperationalError("COMMIT", None, psycopg.OperationalError("server closed the connection unexpectedly"),
                           connection_invalidated=True)


@pytest.mark.parametrize("fault", ["connection", "statement"])
def test_a_lost_connection_mid_run_hands_the_job_to_the_reaper(own_settings, hopper_file, monkeypatch, fault):
    """The database ends the worker's connection while it records an evaluation: the attempt records nothing (it
    cannot) and is not a failure of the job; the reaper re-queues it once its heartbeat is stale, and the next attempt
    resumes from the checkpoint and succeeds. A statement's own error on a live connection (here a statement timeout)
    is the job's failure, recorded at once. On a database of the test's own, so no other worker's reaper takes it."""
    from kernel.db import make_engine, make_sessionmaker
    from kernel.models import JobEvaluation, Owner
    from worker.callback import DbCallback
    from worker.reaper import reap

    engine = make_engine(own_settings.database_url)
    sessions = make_sessionmaker(engine)
    with sessions.begin() as s:
        owner = Owner(id=new_id("own"), name=f"blip-{new_id('x')}")
        dataset = Dataset(id=new_id("ds"), owner_id=owner.id, name="hopper", format="hdf5", sha256="",
                          size_bytes=1, path=str(hopper_file), env="hopper", obs_dim=11, act_dim=3, report={})
        s.add(owner)
        s.flush()
        s.add(dataset)
        job = Job(id=new_id("job"), owner_id=owner.id, dataset_id=dataset.id, algorithm="mopo", env="hopper",
                  preset="smoke", overrides={}, seed=0, status="queued", max_attempts=3, max_runtime_s=600,
                  config=build_config("mopo", env="hopper", preset="smoke", overrides={"epochs": 2}).model_dump(
                      mode="json"))
        s.add(job)
    real, dropped = DbCallback.on_evaluation, []

    def dropping(self, epoch, mean_return, normalized_score):
        if epoch == 2 and not dropped:
            dropped.append(epoch)
            with self.sessions.begin() as s:
                if fault == "connection":
                    s.execute(text("SELECT pg_terminate_backend(pg_backend_pid())"))
                s.execute(text("SET LOCAL statement_timeout = 1"))
                s.execute(text("SELECT pg_sleep(1)"))
        return real(self, epoch, mean_return, normalized_score)

    monkeypatch.setattr(runner, "FINISH_RETRY_S", ())
    monkeypatch.setattr(DbCallback, "on_evaluation", dropping)
    try:
        if fault == "statement":
            assert run_job(own_settings, sessions, job.id) == "failed" and dropped == [2]
            with sessions() as s:
                row = s.get(Job, job.id)
                assert (row.status, row.attempts, row.error_code) == ("failed", 1, "internal_error")
                assert "database error (OperationalError)" in row.error_message
            return
        assert run_job(own_settings, sessions, job.id) == "interrupted" and dropped == [2]
        with sessions() as s:
            row = s.get(Job, job.id)
            assert (row.status, row.attempts, row.error_code) == ("running", 1, None)
        stale = own_settings.model_copy(update={"stale_after_s": 0})
        assert reap(sessions, stale, lambda job_id, runtime: None) == [job.id]
        assert run_job(own_settings, sessions, job.id) == "succeeded"
        with sessions() as s:
            row = s.get(Job, job.id)
            epochs = s.scalars(select(JobEvaluation.epoch).where(JobEvaluation.job_id == job.id)
                               .order_by(JobEvaluation.epoch)).all()
            messages = s.scalars(select(JobEvent.message).where(JobEvent.job_id == job.id, JobEvent.type == "status")
                                 .order_by(JobEvent.id)).all()
        assert (row.status, row.attempts, row.error_code) == ("succeeded", 2, None)
        assert epochs == [1, 2], "one history: the lost attempt's epoch 1, the resumed attempt's epoch 2"
        assert messages[1].startswith("re-queued") and messages[1].endswith("will resume from checkpoint")
    finally:
        engine.dispose()
