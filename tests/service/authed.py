"""A client that acts as one owner."""
from __future__ import annotations

from drop_client import DropClient


class Authed:
    """A TestClient that sends one owner's bearer token, for requests whose raw answer a test checks; `api` is the
    drop_client on the same connection and token."""

    def __init__(self, client, token: str):
        self.client, self.headers = client, {"Authorization": f"Bearer {token}"}
        self.api = DropClient(token=token, http=client)

    def request(self, method: str, url: str, headers: dict | None = None, **kw):
        return self.client.request(method, url, headers={**self.headers, **(headers or {})}, **kw)

    def get(self, url, **kw):
        return self.request("GET", url, **kw)

    def head(self, url, **kw):
        return self.request("HEAD", url, **kw)

    def post(self, url, **kw):
        return self.request("POST", url, **kw)

    def delete(self, url, **kw):
        return self.request("DELETE", url, **kw)
