"""Fixtures for the service tests: a throwaway PostgreSQL database, a private Redis queue, a real Celery worker
process, the API in-process over the real database and broker, a small real dataset, and a check that a test leaves
no upload behind. Helpers that are not fixtures are in the modules beside this one."""
from __future__ import annotations

import secrets
from pathlib import Path

import pytest
import redis

from kernel.settings import Settings

from .authed import Authed
from .backends import REDIS_URL, database
from .processes import start_worker, stop_worker


@pytest.fixture(scope="session")
def hopper_file(tmp_path_factory) -> Path:
    from drop_engine.collect import collect_transitions, random_policy
    from drop_engine.data import save_hdf5

    path = tmp_path_factory.mktemp("data") / "hopper-random.hdf5"
    save_hdf5(path, collect_transitions("hopper", random_policy(3, 0), 2000, seed=0), {"env_name": "Hopper-v4"})
    return path


@pytest.fixture(scope="session")
def pg_url():
    with database() as url:
        yield url


@pytest.fixture
def own_settings(settings):
    """Settings on a migrated database and a queue of the test's own: its workers' reapers see only its jobs."""
    from kernel.db import upgrade

    with database() as url:
        upgrade(url)
        yield settings.model_copy(update={"database_url": url, "queue": f"{settings.queue}-{secrets.token_hex(3)}"})


@pytest.fixture(scope="session")
def settings(tmp_path_factory, pg_url) -> Settings:
    from kernel.db import upgrade

    queue = f"drop-test-{secrets.token_hex(4)}"
    s = Settings(data_dir=tmp_path_factory.mktemp("drop-data"), database_url=pg_url, broker_url=REDIS_URL, queue=queue,
                 max_upload_bytes=2_000_000, heartbeat_s=1.0, cancel_poll_s=0.1, worker_threads=1,
                 validate_memory_bytes=4 * 1024**3)
    s.ensure_dirs()
    upgrade(pg_url)
    yield s
    client = redis.Redis.from_url(REDIS_URL)
    for key in client.scan_iter(f"{queue}*"):
        client.delete(key)


@pytest.fixture(scope="session")
def worker(settings, tmp_path_factory):
    """One real `drop worker` process consuming the test queue."""
    proc = start_worker(settings, tmp_path_factory.mktemp("logs") / "worker.log")
    yield proc
    stop_worker(proc)


@pytest.fixture(scope="session")
def app(settings):
    from app.main import create_app

    return create_app(settings)


@pytest.fixture(scope="session")
def tokens(app) -> dict[str, str]:
    from app.core.auth import create_token

    return {name: create_token(app.state.sessions, name) for name in ("alice", "bob")}


@pytest.fixture(scope="session")
def client(app):
    from fastapi.testclient import TestClient

    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


@pytest.fixture
def alice(client, tokens):
    return Authed(client, tokens["alice"])


@pytest.fixture
def bob(client, tokens):
    return Authed(client, tokens["bob"])


def _leftovers(settings) -> list[Path]:
    """What is in the folders an upload writes to."""
    return [p for sub in ("uploads", "datasets") for p in (settings.data_dir / sub).iterdir()]


@pytest.fixture
def clean(settings, alice):
    """The test leaves no file in the upload folders and no dataset of alice's behind."""
    before_files = set(_leftovers(settings))
    before_ids = {d["id"] for d in alice.get("/v1/datasets", params={"limit": 100}).json()["data"]}
    yield
    assert set(_leftovers(settings)) == before_files
    assert {d["id"] for d in alice.get("/v1/datasets", params={"limit": 100}).json()["data"]} == before_ids
