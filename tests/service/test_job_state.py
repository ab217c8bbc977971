"""The job state machine's table, move by move, on PostgreSQL and SQLite: every allowed move happens with its status
event; every forbidden one leaves the row and its events as they were and says so (False, or ForbiddenTransition when
the writer names the forbidden source); and a worker's moves happen only while the row is still its attempt."""
from __future__ import annotations

import itertools

import pytest
from sqlalchemy import select

from kernel.db import make_sessionmaker
from kernel.ids import new_id
from kernel.job_state import ATTEMPT, TRANSITIONS, ForbiddenTransition, JobStatus, transition
from kernel.models import Job, JobEvent

from .backends import migrated_engine

PAIRS = list(itertools.product(JobStatus, JobStatus))
ALLOWED = [(a, b) for a, b in PAIRS if b in TRANSITIONS[a]]
OWNER = "own_states"


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def sessions(request, tmp_path_factory):
    """A migrated database of the module's own: no worker's reaper sends its queued jobs."""
    with migrated_engine(request.param, tmp_path_factory.mktemp("job-state"), OWNER) as engine:
        yield make_sessionmaker(engine)


def _job(sessions, status: JobStatus, attempts: int = 1) -> str:
    job_id = new_id("job")
    with sessions.begin() as s:
        s.add(Job(id=job_id, owner_id=OWNER, algorithm="drop", env="hopper", preset="smoke", overrides={}, seed=0,
                  config={}, status=status.value, attempts=attempts, max_attempts=3, max_runtime_s=600))
    return job_id


def _row(sessions, job_id: str) -> tuple:
    """The job's status, its worker column (what the move sets) and its events."""
    with sessions() as s:
        job = s.get(Job, job_id)
        events = [tuple(e) for e in s.execute(select(JobEvent.message, JobEvent.data).where(JobEvent.job_id == job_id))]
        return job.status, job.worker, events


def _move(sessions, job_id: str, target: JobStatus, **fence) -> bool:
    with sessions.begin() as s:
        return transition(s, job_id, target, values={"worker": "w1"}, message="moved", data={"by": "test"}, **fence)


def _moved_to(target: JobStatus) -> tuple:
    return target.value, "w1", [("moved", {"status": target.value, "by": "test"})]


@pytest.mark.parametrize("named", [False, True], ids=["any-source", "named-source"])
@pytest.mark.parametrize("source,target", PAIRS, ids=[f"{a}->{b}" for a, b in PAIRS])
def test_every_move(sessions, source, target, named):
    job_id = _job(sessions, source)
    fence = {"source": source} if named else {}
    if target in TRANSITIONS[source]:
        assert _move(sessions, job_id, target, **fence) is True
        assert _row(sessions, job_id) == _moved_to(target)
    elif named:
        with pytest.raises(ForbiddenTransition, match=f"from {source} to {target}"):
            _move(sessions, job_id, target, **fence)
        assert _row(sessions, job_id) == (source.value, None, [])
    else:
        assert _move(sessions, job_id, target) is False
        assert _row(sessions, job_id) == (source.value, None, [])


@pytest.mark.parametrize("source,target", ALLOWED, ids=[f"{a}->{b}" for a, b in ALLOWED])
def test_a_worker_moves_only_its_own_attempt(sessions, source, target):
    job_id = _job(sessions, source, attempts=2)
    assert _move(sessions, job_id, target, attempt=1) is False  # the row is another attempt's
    assert _row(sessions, job_id) == (source.value, None, [])
    mine = source in ATTEMPT  # a queued job is no attempt's
    assert _move(sessions, job_id, target, attempt=2) is mine
    assert _row(sessions, job_id) == (_moved_to(target) if mine else (source.value, None, []))


def test_a_named_source_must_be_the_row_status(sessions):
    job_id = _job(sessions, JobStatus.RUNNING)
    assert _move(sessions, job_id, JobStatus.CANCELLED, source=JobStatus.QUEUED) is False  # cancel's first try
    assert _row(sessions, job_id) == ("running", None, [])
