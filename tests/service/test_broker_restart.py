"""Redis restarted (without persistence) while one job runs and another waits: the running job finishes, and the
queued one, whose message died with Redis, is sent again by the idle worker's reaper and runs once. A redis-server of
the test's own, on a free port, so the shared one is never touched."""
from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import pytest
import redis

from .authed import Authed
from .processes import free_port, start_worker, stop_worker


class RedisServer:
    def __init__(self, workdir: Path):
        self.port, self.workdir, self.proc = free_port(), workdir, None
        self.url = f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        binary = shutil.which("redis-server")
        assert binary, "redis-server is not on PATH"
        self.proc = subprocess.Popen([binary, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "",
                                      "--appendonly", "no", "--daemonize", "no", "--dir", str(self.workdir)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
        client = redis.Redis.from_url(self.url)
        deadline = time.monotonic() + 10
        while True:
            try:
                client.ping()
                return
            except redis.ConnectionError:
                assert time.monotonic() < deadline and self.proc.poll() is None, "redis-server did not start"
                time.sleep(0.05)

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait()


@pytest.fixture
def own_redis(tmp_path):
    server = RedisServer(tmp_path)
    server.start()
    yield server
    server.kill()


def test_jobs_survive_a_redis_restart(own_settings, own_redis, hopper_file, tmp_path):
    from fastapi.testclient import TestClient

    from app.core.auth import create_token
    from app.main import create_app

    settings = own_settings.model_copy(update={"broker_url": own_redis.url, "reap_every_s": 0.5,
                                               "redeliver_after_s": 2.0})
    log = tmp_path / "worker.log"
    worker = start_worker(settings, log)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            alice = Authed(client, create_token(client.app.state.sessions, "alice"))
            ds = alice.api.upload_dataset(hopper_file)
            spec = {"dataset_id": ds["id"], "preset": "smoke"}
            running = alice.post("/v1/jobs", json={**spec, "overrides": {"epochs": 10}}).json()
            queued = alice.post("/v1/jobs", json={**spec, "seed": 1}).json()
            deadline = time.monotonic() + 120  # imports, dynamics and DICE in a niced pool on a loaded machine
            while True:
                job = alice.get(f"/v1/jobs/{running['id']}").json()
                if job["status"] == "running" and (job["progress"] or {}).get("phase") == "train":
                    break
                assert job["status"] in ("queued", "running") and time.monotonic() < deadline, job
                time.sleep(0.1)
            assert alice.get(f"/v1/jobs/{queued['id']}").json()["status"] == "queued"  # one slot, and it is busy
            assert redis.Redis.from_url(own_redis.url).llen(settings.queue) == 1

            own_redis.kill()  # every message goes with it
            own_redis.start()
            assert redis.Redis.from_url(own_redis.url).llen(settings.queue) == 0, "the queued message is gone"

            for job_id in (running["id"], queued["id"]):
                done = alice.api.wait(job_id, timeout=120)
                assert done["status"] == "succeeded" and done["attempts"] == 1, done
        assert f"re-sent jobs {queued['id']}" in log.read_text()
    finally:
        stop_worker(worker)
