"""Fixtures for the service tests: a throwaway PostgreSQL database, a private Redis queue, a real Celery worker
process, the API in-process over the real database and broker, and small real datasets."""
from __future__ import annotations

import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import httpx
import psycopg
import pytest
import redis

from kernel.settings import Settings
from drop_client import ApiError, DropClient

PG_ADMIN = "postgresql://postgres@127.0.0.1:5432/postgres"
REDIS_URL = "redis://127.0.0.1:6379/0"
REPO = Path(__file__).resolve().parents[2]


def settings_env(settings: Settings) -> dict[str, str]:
    """The DROP_ environment that makes a subprocess see the same settings."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("DROP_")}
    for name, value in settings.model_dump().items():
        if value is not None:
            env[f"DROP_{name.upper()}"] = str(value)
    return env


@pytest.fixture(scope="session")
def hopper_file(tmp_path_factory) -> Path:
    from drop_engine.collect import collect_transitions, random_policy
    from drop_engine.data import save_hdf5

    path = tmp_path_factory.mktemp("data") / "hopper-random.hdf5"
    save_hdf5(path, collect_transitions("hopper", random_policy(3, 0), 2000, seed=0), {"env_name": "Hopper-v4"})
    return path


@contextmanager
def database() -> Iterator[str]:
    """A new empty PostgreSQL database, dropped afterwards."""
    name = f"drop_test_{secrets.token_hex(4)}"
    with psycopg.connect(PG_ADMIN, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    try:
        yield f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}"
    finally:
        with psycopg.connect(PG_ADMIN, autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_line(path: Path, needle: str, proc: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if needle in path.read_text(errors="replace"):
            return
        if proc.poll() is not None:
            break
        time.sleep(0.2)
    raise RuntimeError(f"{needle!r} not seen; log:\n{path.read_text(errors='replace')[-4000:]}")


def wait_ready(http: httpx.Client, proc: subprocess.Popen, log: Path, timeout: float = 60) -> None:
    """Poll the server's /readyz until it answers 200; fail with its log if it exits or never does."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            if http.get("/readyz").status_code == 200:
                return
        except httpx.TransportError:
            pass
        assert time.monotonic() < deadline and proc.poll() is None, log.read_text(errors="replace")[-4000:]
        time.sleep(0.2)


def start_worker(settings: Settings, log: Path, repo: Path = REPO) -> subprocess.Popen:
    """A `drop worker` (of the code in `repo`) in a process group of its own, so kill_group takes its pool children
    with it."""
    with log.open("ab") as out:
        proc = subprocess.Popen([sys.executable, "-m", "app.cli", "worker", "--concurrency", "1"], cwd=repo,
                                env=settings_env(settings), stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
    try:
        wait_for_line(log, " ready.", proc, 60)
    except BaseException:
        kill_group(proc)
        raise
    return proc


def kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL a worker and its pool children: a crash, with no chance to checkpoint or hand the job back."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def stop_worker(proc: subprocess.Popen) -> None:
    """Warm shutdown, or a kill if it takes too long."""
    proc.terminate()
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        kill_group(proc)


def past_first_epoch(job: dict) -> bool:
    """A `wait` condition: the job is running and has trained an epoch, so it has a checkpoint to resume from."""
    return job["status"] == "running" and (job["progress"] or {}).get("epoch", 0) >= 1


class Api:
    """`drop api` over `settings` on a port of its own, in a process of its own."""

    def __init__(self, settings: Settings, log: Path):
        self.port, self.env, self.log, self.proc = free_port(), settings_env(settings), log, None
        self.url = f"http://127.0.0.1:{self.port}"

    def start(self) -> None:
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "drop_cli", "api", "--host", "127.0.0.1",
                                          "--port", str(self.port)], cwd=REPO, env=self.env, stdout=out,
                                         stderr=subprocess.STDOUT)
        with httpx.Client(base_url=self.url) as http:
            wait_ready(http, self.proc, self.log)

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(20)


class Serve:
    """`drop serve` with a data directory under `tmp_path` and nothing else: SQLite, the filesystem broker, no auth."""

    def __init__(self, tmp_path: Path):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("DROP_")}
        self.env.update(DROP_DATA_DIR=str(tmp_path / "data"), DROP_WORKER_THREADS="1")
        self.log_path = tmp_path / "serve.log"
        self.proc = None

    def start(self) -> DropClient:
        with self.log_path.open("ab") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "drop_cli", "serve", "--port", str(self.port)],
                                         cwd=REPO, env=self.env, stdout=log, stderr=subprocess.STDOUT)
        drop = DropClient(self.url)
        wait_ready(drop.http, self.proc, self.log_path)
        return drop

    def stop(self, sig: signal.Signals = signal.SIGINT, timeout: float = 60) -> int:
        self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise


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
    return _Authed(client, tokens["alice"])


@pytest.fixture
def bob(client, tokens):
    return _Authed(client, tokens["bob"])


class _Authed:
    """A TestClient that sends one owner's bearer token, for requests whose raw answer a test checks; `api` is the
    drop_client on the same connection and token."""

    def __init__(self, client, token: str):
        self.client, self.headers = client, {"Authorization": f"Bearer {token}"}
        self.api = DropClient(token=token, http=client)

    def request(self, method: str, url: str, headers: dict | None = None, **kw):
        return self.client.request(method, url, headers={**self.headers, **(headers or {})}, **kw)

    def get(self, url, **kw):
        return self.request("GET", url, **kw)

    def post(self, url, **kw):
        return self.request("POST", url, **kw)

    def delete(self, url, **kw):
        return self.request("DELETE", url, **kw)


def upload_refused(api: DropClient, path: Path) -> httpx.Response:
    """The answer to an upload that must fail."""
    with pytest.raises(ApiError) as refused:
        api.upload_dataset(path)
    return refused.value.response
