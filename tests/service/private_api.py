"""An API of a test's own over the session's database: a fresh owner, and a private queue that no worker reads, so
its jobs stay queued (nothing trains) until they are cancelled on the way out."""
from __future__ import annotations

import io
import secrets
from contextlib import contextmanager
from typing import Iterator

import numpy as np
import redis

from .conftest import REDIS_URL


def tiny_npz(seed: int) -> bytes:
    """A 40-transition hopper-shaped dataset, different for each seed."""
    rng, n = np.random.default_rng(seed), 40
    buf = io.BytesIO()
    np.savez(buf, observations=rng.normal(size=(n, 11)).astype(np.float32),
             actions=rng.uniform(-1, 1, size=(n, 3)).astype(np.float32),
             rewards=rng.normal(size=n).astype(np.float32), terminals=np.zeros(n, bool))
    return buf.getvalue()


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
