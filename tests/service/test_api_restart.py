"""The API process killed and started again while jobs run, in the production layout (`drop api` and `drop worker` as
separate processes on PostgreSQL and Redis): the worker never notices, nothing is lost, and a client that polls, or
resumes its event stream with Last-Event-ID, carries on against the new process."""
from __future__ import annotations

import signal
import subprocess
import sys
import time

import httpx
import pytest

from .processes import REPO, free_port, settings_env, start_worker, stop_worker, wait_ready


class Api:
    def __init__(self, settings, log):
        self.port, self.env, self.log, self.proc = free_port(), settings_env(settings), log, None

    def start(self) -> None:
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "app.cli", "api", "--host", "127.0.0.1",
                                          "--port", str(self.port)], cwd=REPO, env=self.env, stdout=out,
                                         stderr=subprocess.STDOUT)
        with httpx.Client(base_url=f"http://127.0.0.1:{self.port}") as http:
            wait_ready(http, self.proc, self.log)

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()


def _events_after(http: httpx.Client, job_id: str, last_id: int) -> list[int]:
    """The ids the SSE stream sends from Last-Event-ID until the server ends it (the job finished)."""
    events = []
    with http.stream("GET", f"/v1/jobs/{job_id}/events",
                     headers={"Accept": "text/event-stream", "Last-Event-ID": str(last_id)}) as r:
        assert r.status_code == 200
        for line in r.iter_lines():
            if line.startswith("id: "):
                events.append(int(line[4:]))
    return events


def test_jobs_and_clients_survive_an_api_restart(own_settings, hopper_file, tmp_path):
    from app.core.auth import create_token
    from kernel.db import make_engine, make_sessionmaker

    token = create_token(make_sessionmaker(make_engine(own_settings.database_url)), "alice")
    worker = start_worker(own_settings, tmp_path / "worker.log")
    api = Api(own_settings, tmp_path / "api.log")
    api.start()
    http = httpx.Client(base_url=f"http://127.0.0.1:{api.port}", headers={"Authorization": f"Bearer {token}"},
                        timeout=30)
    try:
        with hopper_file.open("rb") as fh:
            ds = http.post("/v1/datasets", files={"file": (hopper_file.name, fh, "application/x-hdf5")}).json()
        spec = {"dataset_id": ds["id"], "preset": "smoke", "overrides": {"epochs": 8, "steps_per_epoch": 40}}
        running = http.post("/v1/jobs", json=spec).json()
        queued = http.post("/v1/jobs", json={**spec, "seed": 1}).json()
        deadline = time.monotonic() + 90
        while (job := http.get(f"/v1/jobs/{running['id']}").json())["status"] != "running" \
                or (job["progress"] or {}).get("epoch", 0) < 1:
            assert job["status"] in ("queued", "running"), job
            assert time.monotonic() < deadline, job
            time.sleep(0.1)
        seen = http.get(f"/v1/jobs/{running['id']}/events", params={"limit": 1000}).json()["data"]

        api.kill()
        with pytest.raises(httpx.TransportError):
            http.get("/healthz")
        time.sleep(2)  # the worker goes on training and recording meanwhile
        api.start()

        for job_id in (running["id"], queued["id"]):
            deadline = time.monotonic() + 120
            while (job := http.get(f"/v1/jobs/{job_id}").json())["status"] not in ("succeeded", "failed",
                                                                                    "cancelled"):
                assert time.monotonic() < deadline, job
                time.sleep(0.25)
            assert job["status"] == "succeeded" and job["attempts"] == 1, job

        # The stream resumed from the last event seen before the restart delivers exactly the rest, in order.
        everything = http.get(f"/v1/jobs/{running['id']}/events", params={"limit": 1000}).json()["data"]
        assert [e["id"] for e in everything[:len(seen)]] == [e["id"] for e in seen]
        assert _events_after(http, running["id"], seen[-1]["id"]) == [e["id"] for e in everything[len(seen):]]
        assert everything[-1]["message"] == "succeeded"
        assert [e["epoch"] for e in http.get(f"/v1/jobs/{running['id']}/evaluations").json()["data"]] == \
            list(range(1, 9))
        assert http.get(f"/v1/jobs/{running['id']}/policy").status_code == 200
    finally:
        http.close()
        if api.proc.poll() is None:
            api.proc.terminate()
            api.proc.wait(20)
        stop_worker(worker)
