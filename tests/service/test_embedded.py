"""`drop serve` end to end: SQLite, Celery's filesystem transport and one embedded worker, nothing else. Stopping it
mid-job by SIGTERM, SIGINT or SIGHUP (or killing it) stops its whole process tree, checkpoints and re-queues the job,
and the next `drop serve` finishes it from that checkpoint."""
from __future__ import annotations

import io
import os
import signal
import sqlite3
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import httpx
import pytest
import torch

from .processes import REPO, free_port, wait_ready


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

    def stop(self, sig: signal.Signals = signal.SIGINT, timeout: float = 60) -> int:
        self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise


def _stat(pid: int) -> list[str] | None:
    """/proc/PID/stat's fields after the command (state, parent, ...); None for a process that is gone or a zombie."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return fields if fields[0] != "Z" else None


def _tree(root: int) -> set[int]:
    """`root` and every live process below it."""
    children: dict[int, list[int]] = defaultdict(list)
    for pid in (int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit()):
        if fields := _stat(pid):
            children[int(fields[1])].append(pid)
    tree, todo = {root}, [root]
    while todo:
        for child in children[todo.pop()]:
            tree.add(child)
            todo.append(child)
    return tree


def _wait(http, job_id, until, timeout=120) -> dict:
    deadline = time.monotonic() + timeout
    while not until(job := http.get(f"/v1/jobs/{job_id}").json()):
        assert time.monotonic() < deadline and job["status"] not in ("failed", "cancelled"), job
        time.sleep(0.2)
    return job


def _assert_ended(pids: set[int], grace_s: float = 10) -> None:
    """Every process ended within `grace_s`: multiprocessing's helpers (the validation's forkserver, the resource
    tracker) end by themselves once they see their parent gone, a moment after it."""
    deadline = time.monotonic() + grace_s
    while left := [pid for pid in pids if _stat(pid)]:
        assert time.monotonic() < deadline, {pid: Path(f"/proc/{pid}/cmdline").read_bytes() for pid in left}
        time.sleep(0.2)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGKILL], ids=lambda s: s.name)
def test_drop_serve_end_to_end_across_a_restart(tmp_path, hopper_file, sig):
    """SIGKILL leaves no chance to stop the worker: it stops by itself when its parent dies."""
    serve = Serve(tmp_path)
    http = serve.start()
    try:
        ds = http.post("/v1/datasets", content=hopper_file.read_bytes(),
                       headers={"Content-Type": "application/x-hdf5"}).json()  # no token: auth is off
        job = http.post("/v1/jobs", json={"dataset_id": ds["id"], "preset": "smoke", "algorithm": "mopo",
                                          "overrides": {"epochs": 30}}).json()  # still running when stopped
        assert job["status"] == "queued", job
        _wait(http, job["id"], lambda j: j["status"] == "running" and (j["progress"] or {}).get("epoch", 0) >= 1)
        tree = _tree(serve.proc.pid)
        assert len(tree) >= 3, "drop serve, its worker and the worker's pool process running the job"
    finally:
        http.close()
        assert serve.stop(sig) == (-sig if sig == signal.SIGKILL else 0), serve.log_path.read_text()[-3000:]
    _assert_ended(tree)
    with sqlite3.connect(tmp_path / "data" / "drop.db") as db:
        assert db.execute("SELECT status FROM jobs WHERE id = ?", (job["id"],)).fetchone() == ("queued",)
        checkpoints = [Path(p) for (p,) in db.execute("SELECT path FROM job_checkpoints WHERE job_id = ?", (job["id"],))]
    assert checkpoints and all(p.is_file() for p in checkpoints)

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
