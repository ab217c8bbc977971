"""`drop serve` end to end: SQLite, Celery's filesystem transport and one embedded worker, nothing else. Stopping it
mid-job by SIGTERM, SIGINT or SIGHUP (or killing it) stops its whole process tree, checkpoints and re-queues the job,
and the next `drop serve` finishes it from that checkpoint."""
from __future__ import annotations

import signal
import sqlite3
import time
from collections import defaultdict
from pathlib import Path

import pytest
import torch

from app.serving.embedded import WORKER_STOP_S

from .processes import Serve, past_first_epoch


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
    drop = serve.start()
    try:
        ds = drop.upload_dataset(hopper_file)  # no token: auth is off
        job = drop.create_job(ds["id"], preset="smoke", algorithm="mopo",
                              overrides={"epochs": 30})  # still running when stopped
        assert job["status"] == "queued", job
        job = drop.wait(job["id"], until=past_first_epoch, timeout=120, poll_s=0.2)
        assert job["status"] == "running", job
        tree = _tree(serve.proc.pid)
        assert len(tree) >= 3, "drop serve, its worker and the worker's pool process running the job"
    finally:
        drop.close()
        assert serve.stop(sig) == (-sig if sig == signal.SIGKILL else 0), serve.log_path.read_text()[-3000:]
    # Killed, `drop serve` cannot stop its worker: the worker's own warm shutdown (the niced pool's final checkpoint)
    # ends the tree, which on a loaded machine takes as long as `drop serve` gives it otherwise.
    _assert_ended(tree, WORKER_STOP_S + 30 if sig == signal.SIGKILL else 10)
    with sqlite3.connect(tmp_path / "data" / "drop.db") as db:
        assert db.execute("SELECT status FROM jobs WHERE id = ?", (job["id"],)).fetchone() == ("queued",)
        rows = db.execute("SELECT path FROM job_checkpoints WHERE job_id = ?", (job["id"],))
        checkpoints = [tmp_path / "data" / p for (p,) in rows]  # stored relative to the data dir
    assert checkpoints and all(p.is_file() for p in checkpoints)

    drop = serve.start()
    try:
        job = drop.wait(job["id"], timeout=120, poll_s=0.2)
        assert job["status"] == "succeeded", job
        assert job["attempts"] == 1, "a shutdown does not use up an attempt"
        events = list(drop.list_events(job["id"]))
        messages = [e["message"] for e in events]
        assert any(m.startswith("re-queued: its worker is shutting down") for m in messages), messages
        resumed = max(i for i, m in enumerate(messages) if m.startswith("running"))
        assert not any(e["type"] == "progress" and e["data"]["phase"] == "dynamics" for e in events[resumed:])
        policy = torch.jit.load(drop.download_policy(job["id"], tmp_path / "policy.pt"))
        assert policy(torch.zeros(1, 11)).shape == (1, 3)
    finally:
        drop.close()
        serve.stop()
    assert (tmp_path / "data" / "drop.db").is_file()
    assert all((tmp_path / "data" / "jobs" / job["id"] / "policy" / which / "policy.pt").is_file()
               for which in ("last", "best"))
