"""A dataset's delete beside a job's creation on it, on SQLite (the embedded mode) and PostgreSQL: one of them wins,
every time. Either the job is created and the delete answers 409 (the dataset stays), or the delete answers 204 and
the job 404; never both, never a 500."""
from __future__ import annotations

import asyncio
import random

import httpx
import pytest
from sqlalchemy import func, select

from app.core.auth import hash_token
from kernel.db import upgrade
from kernel.ids import new_id
from kernel.models import Dataset, Job, Token

from .private_api import private_api

PAIRS = 30


def _dataset(sessions, owner: str) -> str:
    """A dataset row of a tiny hopper dataset (its file is never read: no worker takes these jobs)."""
    report = {"transitions": 40, "obs_dim": 11, "act_dim": 3, "env": "hopper", "env_candidates": ["hopper"]}
    row = Dataset(id=new_id("ds"), owner_id=owner, name="race", format="npz", sha256="0" * 64, size_bytes=1,
                  decoded_bytes=1, path="/nonexistent", env="hopper", obs_dim=11, act_dim=3, report=report)
    with sessions.begin() as s:
        s.add(row)
    return row.id


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_delete_beside_create_has_one_winner(settings, tmp_path, backend):
    overrides = {}
    if backend == "sqlite":
        overrides["database_url"] = f"sqlite:///{tmp_path / 'race.db'}"
        upgrade(overrides["database_url"])
    with private_api(settings, max_active_jobs_per_owner=PAIRS + 1, **overrides) as (app, client):
        token = client.headers["authorization"].split()[1]
        with app.state.sessions() as s:
            owner_id = s.scalar(select(Token.owner_id).where(Token.token_hash == hash_token(token)))
        rng = random.Random(0)

        async def pair(c: httpx.AsyncClient, dataset_id: str) -> tuple[httpx.Response, httpx.Response]:
            async def later(coro, delay: float):
                await asyncio.sleep(delay)
                return await coro

            create = c.post("/v1/jobs", json={"dataset_id": dataset_id, "env": "hopper", "preset": "smoke"})
            delete = c.delete(f"/v1/datasets/{dataset_id}")
            return tuple(await asyncio.gather(later(create, rng.uniform(0, 0.01)), later(delete, rng.uniform(0, 0.01))))

        async def run() -> list[tuple[str, httpx.Response, httpx.Response]]:
            transport = httpx.ASGITransport(app=app, raise_app_exceptions=False)  # a 500 is an answer here
            async with httpx.AsyncClient(transport=transport, base_url="http://test", headers=client.headers) as c:
                out = []
                for _ in range(PAIRS):
                    dataset_id = _dataset(app.state.sessions, owner_id)
                    out.append((dataset_id, *await pair(c, dataset_id)))
                return out

        outcomes = {"job first": 0, "delete first": 0}
        for dataset_id, created, deleted in asyncio.run(run()):
            statuses = (created.status_code, deleted.status_code)
            with app.state.sessions() as s:
                kept = s.get(Dataset, dataset_id) is not None
                jobs = s.scalar(select(func.count()).select_from(Job).where(Job.dataset_id == dataset_id))
            if statuses == (201, 409):
                assert deleted.json()["code"] == "dataset_in_use" and kept and jobs == 1
                outcomes["job first"] += 1
            else:
                assert statuses == (404, 204), (created.text, deleted.text)
                assert not kept and created.json()["code"] == "not_found"
                outcomes["delete first"] += 1
        assert sum(outcomes.values()) == PAIRS, outcomes
