"""`drop serve` end to end: SQLite, Celery's filesystem transport and one embedded worker, nothing else."""
from __future__ import annotations

import io
import signal
import socket
import subprocess
import sys
import time

import httpx
import torch

from .conftest import REPO


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_drop_serve_end_to_end(tmp_path, hopper_file):
    import os

    port = _free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("DROP_")}
    env.update(DROP_DATA_DIR=str(tmp_path / "data"), DROP_WORKER_THREADS="1")
    log = (tmp_path / "serve.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "serve", "--port", str(port)], cwd=REPO, env=env,
                            stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=base, timeout=60) as http:
            deadline = time.monotonic() + 60
            while True:
                try:
                    if http.get("/readyz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                assert time.monotonic() < deadline and proc.poll() is None, (tmp_path / "serve.log").read_text()
                time.sleep(0.3)
            ds = http.post("/v1/datasets", content=hopper_file.read_bytes(),
                           headers={"Content-Type": "application/x-hdf5"}).json()  # no token: auth is off
            job = http.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke", "algorithm": "mopo"}).json()
            assert job["status"] == "queued", job
            deadline = time.monotonic() + 120
            while (job := http.get(f"/v1/jobs/{job['id']}").json())["status"] not in ("succeeded", "failed"):
                assert time.monotonic() < deadline, job
                time.sleep(0.5)
            assert job["status"] == "succeeded", http.get(f"/v1/jobs/{job['id']}/events").text
            policy = torch.jit.load(io.BytesIO(http.get(f"/v1/jobs/{job['id']}/policy").content))
            assert policy(torch.zeros(1, 11)).shape == (1, 3)
        assert (tmp_path / "data" / "drop.db").is_file()
        assert (tmp_path / "data" / "jobs" / job["id"] / "policy" / "policy.pt").is_file()
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
