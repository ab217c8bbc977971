"""Of many workers racing to claim one queued job, exactly one wins, on PostgreSQL and on SQLite."""
from __future__ import annotations

import threading

import pytest

from kernel.db import make_engine, make_sessionmaker, upgrade
from kernel.ids import new_id
from kernel.models import Job, Owner
from worker.runner import claim


def _race(url: str, contenders: int = 8) -> list[int | None]:
    engine = make_engine(url)
    sessions = make_sessionmaker(engine)
    with sessions.begin() as s:
        owner = Owner(id=new_id("own"), name=new_id("racer"))
        s.add(owner)
        s.flush()
        job = Job(id=new_id("job"), owner_id=owner.id, algorithm="drop", env="hopper", preset="smoke", overrides={},
                  seed=0, config={}, status="queued", max_attempts=3, max_runtime_s=600)
        s.add(job)
    barrier = threading.Barrier(contenders)
    results: list[int | None] = []

    def contend(i: int) -> None:
        barrier.wait()
        results.append(claim(sessions, job.id, f"w{i}"))

    threads = [threading.Thread(target=contend, args=(i,)) for i in range(contenders)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    with sessions.begin() as s:
        assert s.get(Job, job.id).attempts == 1
        s.delete(s.get(Owner, owner.id))
    engine.dispose()
    return results


@pytest.mark.parametrize("backend", ["postgresql", "sqlite"])
def test_exactly_one_claim_wins(backend, settings, tmp_path):
    url = settings.database_url if backend == "postgresql" else f"sqlite:///{tmp_path / 'race.db'}"
    if backend == "sqlite":
        upgrade(url)
    results = _race(url)
    assert sorted(results, key=lambda r: r is None) == [1] + [None] * 7
