"""A job whose worker is SIGKILLed on every attempt fails once max_attempts is used up, saying so, instead of being
re-queued forever. Real workers on a database and queue of the test's own, each killed while it runs the job."""
from __future__ import annotations

import time

from .conftest import _Authed, kill_group, start_worker, stop_worker


def _wait_running(alice, job_id: str, attempt: int, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = alice.get(f"/v1/jobs/{job_id}").json()
        if job["status"] == "running" and job["attempts"] == attempt:
            return
        assert job["status"] in ("queued", "running"), job
        time.sleep(0.1)
    raise AssertionError(f"attempt {attempt} of {job_id} never started: {job}")


def test_job_fails_after_max_attempts_crashes(own_settings, hopper_file, tmp_path):
    from fastapi.testclient import TestClient

    from app.core.auth import create_token
    from app.main import create_app

    settings = own_settings.model_copy(update={"max_attempts": 2, "stale_after_s": 3.0, "reap_every_s": 0.5})
    log = tmp_path / "workers.log"
    last = None
    with TestClient(create_app(settings), raise_server_exceptions=False) as client:
        alice = _Authed(client, create_token(client.app.state.sessions, "alice"))
        ds = alice.api.upload_dataset(hopper_file)
        job = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke",
                                           "overrides": {"epochs": 500}}).json()
        assert job["max_attempts"] == 2
        try:
            for attempt in (1, 2):  # the next worker's reaper re-queues the job once its heartbeat is stale
                crashing = start_worker(settings, log)
                try:
                    _wait_running(alice, job["id"], attempt)
                finally:
                    kill_group(crashing)
            last = start_worker(settings, log)
            done = alice.api.wait(job["id"], timeout=60)
            assert done["status"] == "failed" and done["attempts"] == 2, done
            assert done["error"]["code"] == "worker_lost"
            assert "attempts exhausted" in done["error"]["message"] and "max_attempts=2" in done["error"]["message"]

            time.sleep(4 * settings.reap_every_s)  # a few more reaper passes change nothing
            assert alice.get(f"/v1/jobs/{job['id']}").json()["status"] == "failed"
            messages = [e["message"] for e in
                        alice.get(f"/v1/jobs/{job['id']}/events", params={"limit": 1000}).json()["data"]]
            assert sum(m.startswith("re-queued") for m in messages) == 1, messages
            assert sum(m.startswith("running (attempt") for m in messages) == 2, messages
            assert messages[-1].startswith("failed: attempts exhausted"), messages
        finally:
            if last is not None:
                stop_worker(last)
