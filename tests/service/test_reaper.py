"""A job whose worker stopped heartbeating is re-queued (and resent), or failed after its last attempt; a job
that never reached the broker is sent again. Runs against the real PostgreSQL database."""
from __future__ import annotations

from datetime import timedelta

from sqlalchemy import select

from app.ids import new_id
from app.models import Job, JobEvent, Owner, utcnow
from worker.reaper import reap
from worker.runner import claim


def _job(s, owner_id: str, **kw) -> Job:
    job = Job(id=new_id("job"), owner_id=owner_id, dataset_id=None, algorithm="drop", env="hopper", preset="smoke",
              overrides={}, seed=0, config={}, max_attempts=2, max_runtime_s=600, **kw)
    s.add(job)
    return job


def test_reaper(app, settings):
    sessions = app.state.sessions
    old = utcnow() - timedelta(seconds=settings.stale_after_s + 60)
    with sessions.begin() as s:
        owner = Owner(id=new_id("own"), name=f"reaper-{new_id('x')}")
        s.add(owner)
        s.flush()
        crashed = _job(s, owner.id, status="running", attempts=1, heartbeat_at=old, enqueued_at=old)
        last_try = _job(s, owner.id, status="running", attempts=2, heartbeat_at=old, enqueued_at=old)
        alive = _job(s, owner.id, status="running", attempts=1, heartbeat_at=utcnow(), enqueued_at=old)
        unsent = _job(s, owner.id, status="queued", attempts=0, created_at=old)
        ids = [j.id for j in (crashed, last_try, alive, unsent)]
    sent: list[str] = []
    assert sorted(reap(sessions, settings, lambda job_id, runtime: sent.append(job_id))) == sorted([crashed.id, unsent.id])
    assert sorted(sent) == sorted([crashed.id, unsent.id])
    with sessions() as s:
        rows = {j.id: j for j in s.scalars(select(Job).where(Job.id.in_(ids)))}
        assert rows[crashed.id].status == "queued" and rows[crashed.id].enqueued_at is not None
        assert rows[last_try.id].status == "failed" and rows[last_try.id].error_code == "worker_lost"
        assert rows[alive.id].status == "running"
        assert s.scalar(select(JobEvent.message).where(JobEvent.job_id == crashed.id)).startswith("re-queued")
    assert reap(sessions, settings, lambda *a: sent.append("again")) == []  # nothing left to do

    # The re-queued job can be claimed exactly once, as attempt 2.
    assert claim(sessions, crashed.id, "w1") == 2
    assert claim(sessions, crashed.id, "w2") is None
    with sessions.begin() as s:  # leave no running rows behind for the session worker's reaper
        s.delete(s.get(Owner, owner.id))
    with sessions() as s:
        assert s.scalar(select(Job.id).where(Job.id.in_(ids))) is None
