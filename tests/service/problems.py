"""Refused requests: the answer to an upload that must fail, and checking a problem+json answer."""
from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from drop_client import ApiError, DropClient

PROBLEM = "application/problem+json"


def assert_problem(r, status: int, *needles: str) -> dict:
    """The answer is a problem+json of `status` whose detail holds each needle, with no traceback; its body."""
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM
    body = r.json()
    assert body["status"] == status and body["title"] and body["type"] and body["code"]
    for needle in needles:
        assert needle in body["detail"], body
    assert "Traceback" not in r.text
    return body


def upload_refused(api: DropClient, path: Path) -> httpx.Response:
    """The answer to an upload that must fail."""
    with pytest.raises(ApiError) as refused:
        api.upload_dataset(path)
    return refused.value.response
