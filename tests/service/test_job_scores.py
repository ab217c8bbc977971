"""The job's score columns follow the engine's rule (best: the earliest of ties; final: the mean of the last three)
through evaluations and through a resumed attempt that drops what a lost one reported after its checkpoint; the lost
attempt's late reports write nothing."""
from __future__ import annotations

import pytest
from sqlalchemy import select, update

from app.core.auth import get_or_create_owner
from kernel.db import make_engine, make_sessionmaker
from kernel.models import Job, JobCheckpoint
from worker.callback import DbCallback


@pytest.fixture
def sessions(own_settings):
    engine = make_engine(own_settings.database_url)
    yield make_sessionmaker(engine)
    engine.dispose()


def _columns(sessions, job_id: str) -> tuple:
    with sessions() as s:
        job = s.get(Job, job_id)
        return job.last_score, job.best_score, job.best_epoch, job.final_score


def test_scores_follow_evaluations_and_a_resume(sessions, own_settings, tmp_path):
    with sessions.begin() as s:
        owner = get_or_create_owner(s, "scores")
        s.add(Job(id="job_scores", owner_id=owner.id, algorithm="drop", env="hopper", preset="smoke", overrides={},
                  seed=0, config={}, status="running", attempts=1, max_attempts=3, max_runtime_s=600))
    here = own_settings.model_copy(update={"data_dir": tmp_path})  # where the checkpoints below are
    first = DbCallback(sessions, "job_scores", 1, here)
    first.on_start(None)
    first.on_evaluation(1, 10.0, 5.0)
    first.on_evaluation(2, 20.0, 9.0)
    checkpoint = tmp_path / "ckpt.pt"
    checkpoint.write_bytes(b"x")
    first.on_checkpoint(checkpoint, 2, 0)
    first.on_evaluation(3, 30.0, 12.0)  # reported after the checkpoint, then the attempt is lost
    assert _columns(sessions, "job_scores") == (12.0, 12.0, 3, (5.0 + 9.0 + 12.0) / 3)

    with sessions.begin() as s:
        s.execute(update(Job).where(Job.id == "job_scores").values(attempts=2))
    second = DbCallback(sessions, "job_scores", 2, here)
    second.on_start((2, 0))
    assert _columns(sessions, "job_scores") == (9.0, 9.0, 2, 7.0)
    second.on_evaluation(3, 15.0, 1.0)
    second.on_evaluation(4, 30.0, 9.0)  # ties the best: epoch 2 stays the best
    assert _columns(sessions, "job_scores") == (9.0, 9.0, 2, (9.0 + 1.0 + 9.0) / 3)

    # The lost attempt's late reports change nothing of the new attempt's: no checkpoint row, no score.
    late = tmp_path / "late.pt"
    late.write_bytes(b"y")
    first.on_checkpoint(late, 5, 0)
    first.on_evaluation(5, 99.0, 99.0)
    with sessions() as s:
        paths = set(s.scalars(select(JobCheckpoint.path).where(JobCheckpoint.job_id == "job_scores")))
    assert paths == {"ckpt.pt"}  # relative to the data dir
    assert _columns(sessions, "job_scores") == (9.0, 9.0, 2, (9.0 + 1.0 + 9.0) / 3)
