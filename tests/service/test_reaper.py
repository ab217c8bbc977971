"""A job whose worker stopped heartbeating is re-queued (and resent), or failed after its last attempt; a job
that never reached the broker is sent again. Runs against the real PostgreSQL database."""
from __future__ import annotations

from datetime import timedelta

import pytest
from sqlalchemy import select, update

from kernel.db import make_engine, make_sessionmaker
from kernel.ids import new_id
from kernel.models import Job, JobCheckpoint, JobEvent, Owner, utcnow
from worker.reaper import reap
from worker.runner import claim


@pytest.fixture
def sessions(own_settings):
    """A database of the test's own: on the shared one the session worker's reaper, which runs at its start-up and
    on its schedule, raced these tests' reaper for their jobs (one it took was missing from the answer asserted)."""
    engine = make_engine(own_settings.database_url)
    yield make_sessionmaker(engine)
    engine.dispose()


def _job(s, owner_id: str, **kw) -> Job:
    job = Job(id=new_id("job"), owner_id=owner_id, dataset_id=None, algorithm="drop", env="hopper", preset="smoke",
              overrides={}, seed=0, config={}, max_attempts=2, max_runtime_s=600, **kw)
    s.add(job)
    return job


def test_reaper(sessions, own_settings):
    old = utcnow() - timedelta(seconds=own_settings.stale_after_s + 60)
    with sessions.begin() as s:
        owner = Owner(id=new_id("own"), name=f"reaper-{new_id('x')}")
        s.add(owner)
        s.flush()
        crashed = _job(s, owner.id, status="running", attempts=1, heartbeat_at=old, enqueued_at=old)
        resumable = _job(s, owner.id, status="running", attempts=1, heartbeat_at=old, enqueued_at=old)
        s.flush()
        s.add(JobCheckpoint(job_id=resumable.id, epoch=3, step=0, path="ckpt-e000003-s000000.pt", size_bytes=1))
        last_try = _job(s, owner.id, status="running", attempts=2, heartbeat_at=old, enqueued_at=old)
        alive = _job(s, owner.id, status="running", attempts=1, heartbeat_at=utcnow(), enqueued_at=old)
        unsent = _job(s, owner.id, status="queued", attempts=0, created_at=old)
        ids = [j.id for j in (crashed, resumable, last_try, alive, unsent)]
    sent: list[str] = []
    reaped = reap(sessions, own_settings, lambda job_id, runtime: sent.append(job_id))
    assert sorted(reaped) == sorted([crashed.id, resumable.id, unsent.id])
    assert sorted(sent) == sorted([crashed.id, resumable.id, unsent.id])
    with sessions() as s:
        rows = {j.id: j for j in s.scalars(select(Job).where(Job.id.in_(ids)))}
        assert rows[crashed.id].status == "queued" and rows[crashed.id].enqueued_at is not None
        assert rows[last_try.id].status == "failed" and rows[last_try.id].error_code == "worker_lost"
        assert rows[alive.id].status == "running"
        # The event says what the next attempt will do: only a job with a checkpoint resumes.
        message = s.scalar(select(JobEvent.message).where(JobEvent.job_id == crashed.id))
        assert message.startswith("re-queued") and message.endswith("will start over (no checkpoint was written)")
        assert s.scalar(select(JobEvent.message).where(JobEvent.job_id == resumable.id)).endswith(
            "will resume from checkpoint")
    assert reap(sessions, own_settings, lambda *a: sent.append("again")) == []  # nothing left to do

    # The re-queued job can be claimed exactly once, as attempt 2.
    assert claim(sessions, crashed.id, "w1") == 2
    assert claim(sessions, crashed.id, "w2") is None
    with sessions.begin() as s:  # an owner's jobs go with it
        s.delete(s.get(Owner, owner.id))
    with sessions() as s:
        assert s.scalar(select(Job.id).where(Job.id.in_(ids))) is None


def test_idle_worker_resends_queued_jobs_whose_message_was_lost(sessions, own_settings):
    """A worker with a free slot takes every message in its queue, so a job still queued after the worker has been
    idle a while, and sent before that, has lost its message (Redis restarted): it is sent again, by one reaper."""
    now = utcnow()
    idle_since = now - timedelta(seconds=own_settings.redeliver_after_s + 5)
    with sessions.begin() as s:
        owner = Owner(id=new_id("own"), name=f"reaper-{new_id('x')}")
        s.add(owner)
        s.flush()
        lost = _job(s, owner.id, status="queued", enqueued_at=idle_since - timedelta(seconds=1))
        fresh = _job(s, owner.id, status="queued", enqueued_at=idle_since + timedelta(seconds=1))
    try:
        sent: list[str] = []
        record = lambda job_id, runtime: sent.append(job_id)  # noqa: E731
        recently_idle = now - timedelta(seconds=own_settings.redeliver_after_s - 5)
        assert lost.id not in reap(sessions, own_settings, record, recently_idle), "idle too briefly to tell"
        assert lost.id not in reap(sessions, own_settings, record, None), "a busy worker cannot tell"
        assert lost.id in reap(sessions, own_settings, record, idle_since)
        again = reap(sessions, own_settings, record, idle_since)
        assert lost.id not in again, "sent once, now enqueued after idle_since"
        assert sent.count(lost.id) == 1 and fresh.id not in sent
        with sessions() as s:
            assert s.get(Job, lost.id).enqueued_at > idle_since and s.get(Job, lost.id).status == "queued"
    finally:
        with sessions.begin() as s:
            s.delete(s.get(Owner, owner.id))


def test_a_heartbeat_between_the_query_and_the_move_keeps_the_job(sessions, own_settings, monkeypatch):
    """The reaper reads the silent jobs, then moves each one: a heartbeat that lands in between means the worker is
    alive, and its job stays running."""
    import worker.reaper as reaper

    with sessions.begin() as s:
        owner = Owner(id=new_id("own"), name=f"reaper-{new_id('x')}")
        s.add(owner)
        s.flush()
        job = _job(s, owner.id, status="running", attempts=1, enqueued_at=utcnow(),
                   heartbeat_at=utcnow() - timedelta(seconds=own_settings.stale_after_s + 60))
    move = reaper.transition

    def heartbeat_first(s, job_id, *args, **kwargs):
        if job_id == job.id:
            with sessions.begin() as other:
                other.execute(update(Job).where(Job.id == job_id).values(heartbeat_at=utcnow()))
        return move(s, job_id, *args, **kwargs)

    monkeypatch.setattr(reaper, "transition", heartbeat_first)
    try:
        assert job.id not in reap(sessions, own_settings, lambda *a: None)
        with sessions() as s:
            assert (s.get(Job, job.id).status, s.get(Job, job.id).attempts) == ("running", 1)
    finally:
        with sessions.begin() as s:
            s.delete(s.get(Owner, owner.id))
