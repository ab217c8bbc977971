"""A client that acts as one owner."""
from __future__ import annotations

import time
from pathlib import Path


class Authed:
    """A TestClient that sends one owner's bearer token."""

    def __init__(self, client, token: str):
        self.client, self.headers = client, {"Authorization": f"Bearer {token}"}

    def request(self, method: str, url: str, headers: dict | None = None, **kw):
        return self.client.request(method, url, headers={**self.headers, **(headers or {})}, **kw)

    def get(self, url, **kw):
        return self.request("GET", url, **kw)

    def post(self, url, **kw):
        return self.request("POST", url, **kw)

    def delete(self, url, **kw):
        return self.request("DELETE", url, **kw)

    def stream(self, method, url, headers=None, **kw):
        return self.client.stream(method, url, headers={**self.headers, **(headers or {})}, **kw)

    def upload(self, path: Path, **kw):
        with open(path, "rb") as fh:
            return self.post("/v1/datasets", files={"file": (path.name, fh, "application/x-hdf5")}, **kw)

    def wait(self, job_id: str, statuses: set[str], timeout: float = 120.0) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            job = self.get(f"/v1/jobs/{job_id}").json()
            if job["status"] in statuses:
                return job
            time.sleep(0.25)
        raise AssertionError(f"job {job_id} still {job['status']} after {timeout} s: {job}")
