"""`drop api --workers 2`: two processes serve one port; the metrics of both are summed on a scrape of either; a
revoked token and a cancelled job look the same from both; killing the supervisor takes its processes with it."""
from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from .datasets import tiny_npz
from .processes import REPO, children, free_port, settings_env, wait_ready
from .scrapes import sample


def test_two_api_processes_share_one_truth(own_settings, tmp_path):
    from app.core.auth import create_token, revoke_token
    from kernel.db import make_engine, make_sessionmaker

    sessions = make_sessionmaker(make_engine(own_settings.database_url))
    token, doomed = create_token(sessions, "alice"), create_token(sessions, "alice")
    port, metrics_dir, log = free_port(), tmp_path / "metrics", tmp_path / "api.log"
    metrics_dir.mkdir()
    env = {**settings_env(own_settings), "PROMETHEUS_MULTIPROC_DIR": str(metrics_dir)}
    with log.open("ab") as out:
        api = subprocess.Popen([sys.executable, "-m", "app.cli", "api", "--host", "127.0.0.1", "--port", str(port),
                                "--workers", "2"], cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        base = f"http://127.0.0.1:{port}"
        with httpx.Client(base_url=base) as http:
            wait_ready(http, api, log)
        deadline = time.monotonic() + 30
        while len(children(api.pid)) < 2:  # the second may still be starting
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        workers = children(api.pid)

        # Each request on a new connection, so both processes take some.
        def call(method: str, path: str, auth: str = token, **kw) -> httpx.Response:
            with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {auth}"}, timeout=30) as one:
                return one.request(method, path, **kw)

        # The kernel spreads new connections over the processes as it likes: call until both have served some.
        calls, deadline = 0, time.monotonic() + 60
        while {int(p.stem.rsplit("_", 1)[1]) for p in metrics_dir.glob("counter_*.db")} != set(workers):
            assert time.monotonic() < deadline, "one process served every request"
            assert call("GET", "/healthz").status_code == 200
            calls += 1
        assert sample(call("GET", "/metrics").text, "drop_http_requests_total", method="GET", route="/healthz",
                      status="200") == calls

        ds = call("POST", "/v1/datasets", content=tiny_npz(2)).json()
        job = call("POST", "/v1/jobs", json={"dataset_id": ds["id"], "env": "hopper", "preset": "smoke"}).json()
        assert call("POST", f"/v1/jobs/{job['id']}/cancel").json()["status"] == "cancelled"
        assert {call("GET", f"/v1/jobs/{job['id']}").json()["status"] for _ in range(10)} == {"cancelled"}

        assert all(call("GET", "/v1/jobs", auth=doomed).status_code == 200 for _ in range(6))  # cached in both
        revoke_token(sessions, doomed)
        time.sleep(own_settings.token_cache_s + 0.5)
        assert {call("GET", "/v1/jobs", auth=doomed).status_code for _ in range(10)} == {401}

        api.send_signal(signal.SIGKILL)
        api.wait()
        deadline = time.monotonic() + 10
        while any(Path(f"/proc/{pid}").exists() and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2]
                  for pid in workers):
            assert time.monotonic() < deadline, "an API process outlived its supervisor"
            time.sleep(0.1)
    finally:
        if api.poll() is None:
            api.kill()
            api.wait()
        sessions.kw["bind"].dispose()
