"""Event streams hold no database connection while they wait, are woken by the job's next event at once on
PostgreSQL, and are bounded per owner."""
from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor, wait
from contextlib import contextmanager
from typing import Iterator

import httpx
import pytest
import uvicorn

from drop_client import DropClient, RateLimited

from .datasets import tiny_npz
from .processes import free_port

STREAMS = 100


@contextmanager
def serving(app) -> Iterator[str]:
    """The app on a real uvicorn server in a thread (TestClient cannot hold many streams open at once)."""
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=free_port(), log_config=None,
                                           access_log=False, timeout_graceful_shutdown=2))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "uvicorn did not start"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{server.config.port}"
    finally:
        server.should_exit = True
        thread.join(10)


def test_hundred_open_streams_leave_the_api_responsive(own_settings, tmp_path):
    from app.core.auth import create_token
    from app.main import create_app

    # No worker reads this queue: the job stays queued, and its streams stay open, until it is cancelled.
    app = create_app(own_settings.model_copy(update={"max_streams_per_owner": STREAMS}))
    token = create_token(app.state.sessions, "streams")
    data = tmp_path / "tiny.npz"
    data.write_bytes(tiny_npz(1))
    opened = [threading.Event() for _ in range(STREAMS)]

    def follow(drop: DropClient, job_id: str, first: threading.Event) -> list[dict]:
        events = []
        for event in drop.stream_events(job_id):
            events.append(event)
            first.set()
        return events

    try:
        # On the way out the server stops first, which ends any stream still open, and then the threads are joined.
        with ThreadPoolExecutor(STREAMS) as pool, serving(app) as base, \
                httpx.Client(base_url=base, limits=httpx.Limits(max_connections=STREAMS + 10), timeout=30) as http:
            drop = DropClient(token=token, http=http)
            job_id = drop.create_job(drop.upload_dataset(data)["id"], env="hopper", preset="smoke")["id"]
            streams = [pool.submit(follow, drop, job_id, first) for first in opened]
            assert all(first.wait(60) for first in opened)  # every stream is open

            # Held connections made every read wait 30 s for the pool, then 500. The median read is under a second;
            # a slow one on a loaded 2-core machine is not the failure this guards.
            seconds = []
            for _ in range(5):
                began = time.perf_counter()
                drop.get_job(job_id)
                seconds.append(time.perf_counter() - began)
            assert sorted(seconds)[2] < 1.0 and max(seconds) < 10, seconds
            with pytest.raises(RateLimited) as refused:
                next(drop.stream_events(job_id))
            assert refused.value.code == "too_many_streams"

            # The cancel's event wakes all streams at once: far sooner than their 15 s safety poll.
            assert app.state.events.live
            drop.cancel_job(job_id)
            _, late = wait(streams, timeout=10)
            assert not late
            for stream in streams:  # each ended with the job (the client raises otherwise) after its two events
                assert [e["data"]["status"] for e in stream.result()] == ["queued", "cancelled"]
            for _ in range(200):  # each stream gives its slot back as it ends
                if not app.state.stream_slots.held():
                    break
                time.sleep(0.1)
            assert app.state.stream_slots.held() == 0
    finally:
        app.state.engine.dispose()
