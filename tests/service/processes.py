"""The service's processes in tests: the environment that gives a subprocess the test's settings, a free port,
waiting for a process to be ready; starting, crashing and stopping a `drop worker`, a `drop api` and a `drop serve`;
and when a job is far enough along to survive its process being killed."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

from app.serving.embedded import WORKER_STOP_S
from drop_client import DropClient
from kernel.settings import Settings

REPO = Path(__file__).resolve().parents[2]


def settings_env(settings: Settings) -> dict[str, str]:
    """The DROP_ environment that makes a subprocess see the same settings."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("DROP_")}
    for name, value in settings.model_dump().items():
        if value is not None:
            env[f"DROP_{name.upper()}"] = str(value)
    return env


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


def children(pid: int) -> list[int]:
    """The child processes of `pid` (multiprocessing's resource tracker left out)."""
    found = [int(c) for task in Path(f"/proc/{pid}/task").iterdir() for c in (task / "children").read_text().split()]
    return [c for c in found if b"resource_tracker" not in Path(f"/proc/{c}/cmdline").read_bytes()]


def niceness(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[16])


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

    def stop(self, sig: signal.Signals = signal.SIGINT, timeout: float = WORKER_STOP_S + 30) -> int:
        """Longer than `drop serve` gives its worker to stop before killing it: on a loaded machine the worker's niced
        pool can take that long, and `drop serve` must get to exit on its own."""
        self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise
