"""`drop serve` end to end: SQLite, Celery's filesystem transport and one embedded worker, nothing else. Stopping it
mid-job checkpoints and re-queues the job, and the next `drop serve` finishes it from that checkpoint."""
from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import time

import httpx
import torch

from .conftest import REPO, free_port, wait_ready


class Serve:
    def __init__(self, tmp_path):
        self.port = free_port()
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("DROP_")}
        self.env.update(DROP_DATA_DIR=str(tmp_path / "data"), DROP_WORKER_THREADS="1")
        self.log_path = tmp_path / "serve.log"
        self.proc = None

    def start(self) -> httpx.Client:
        with self.log_path.open("ab") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "app.cli", "serve", "--port", str(self.port)],
                                         cwd=REPO, env=self.env, stdout=log, stderr=subprocess.STDOUT)
        http = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=60)
        wait_ready(http, self.proc, self.log_path)
        return http

    def stop(self, timeout: float = 60) -> int:
        self.proc.send_signal(signal.SIGINT)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise


def _wait(http, job_id, until, timeout=120) -> dict:
    deadline = time.monotonic() + timeout
    while not until(job := http.get(f"/v1/jobs/{job_id}").json()):
        assert time.monotonic() < deadline and job["status"] not in ("failed", "cancelled"), job
        time.sleep(0.2)
    return job


def test_drop_serve_end_to_end_across_a_restart(tmp_path, hopper_file):
    serve = Serve(tmp_path)
    http = serve.start()
    try:
        ds = http.post("/v1/datasets", content=hopper_file.read_bytes(),
                       headers={"Content-Type": "application/x-hdf5"}).json()  # no token: auth is off
        job = http.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke", "algorithm": "mopo",
                                          "overrides": {"epochs": 5}}).json()
        assert job["status"] == "queued", job
        _wait(http, job["id"], lambda j: j["status"] == "running" and (j["progress"] or {}).get("epoch", 0) >= 1)
    finally:
        http.close()
        assert serve.stop() == 0, serve.log_path.read_text()[-3000:]

    http = serve.start()
    try:
        job = _wait(http, job["id"], lambda j: j["status"] == "succeeded")
        assert job["attempts"] == 1, "a shutdown does not use up an attempt"
        events = http.get(f"/v1/jobs/{job['id']}/events", params={"limit": 1000}).json()["data"]
        messages = [e["message"] for e in events]
        assert any(m.startswith("re-queued: its worker is shutting down") for m in messages), messages
        resumed = max(i for i, m in enumerate(messages) if m.startswith("running"))
        assert not any(e["type"] == "progress" and e["data"]["phase"] == "dynamics" for e in events[resumed:])
        policy = torch.jit.load(io.BytesIO(http.get(f"/v1/jobs/{job['id']}/policy").content))
        assert policy(torch.zeros(1, 11)).shape == (1, 3)
    finally:
        http.close()
        serve.stop()
    assert (tmp_path / "data" / "drop.db").is_file()
    assert all((tmp_path / "data" / "jobs" / job["id"] / "policy" / which / "policy.pt").is_file()
               for which in ("last", "best"))
