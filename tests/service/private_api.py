"""An API of a test's own over the session's database: a fresh owner, and a private queue that no worker reads, so
its jobs stay queued (nothing trains) until they are cancelled on the way out."""
from __future__ import annotations

import secrets
from contextlib import contextmanager
from typing import Iterator

import redis

from .backends import REDIS_URL


@contextmanager
def private_api(settings, **overrides) -> Iterator[tuple]:
    """(app, TestClient sending the new owner's token); `overrides` change settings, e.g. quotas."""
    from fastapi.testclient import TestClient

    from app.core.auth import create_token
    from app.main import create_app

    queue = f"drop-private-{secrets.token_hex(4)}"
    app = create_app(settings.model_copy(update={"queue": queue, **overrides}))
    token = create_token(app.state.sessions, f"private-{secrets.token_hex(4)}")
    try:
        with TestClient(app, raise_server_exceptions=False, headers={"Authorization": f"Bearer {token}"}) as client:
            yield app, client
            for job in client.get("/v1/jobs", params={"limit": 100, "status": "queued"}).json()["data"]:
                client.post(f"/v1/jobs/{job['id']}/cancel")
    finally:
        app.state.engine.dispose()
        broker = redis.Redis.from_url(REDIS_URL)
        for key in broker.scan_iter(f"{queue}*"):
            broker.delete(key)
