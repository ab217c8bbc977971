"""The client's exceptions. An error answer from the API becomes an `ApiError` subclass chosen by its status, carrying
the problem+json fields (RFC 9457), so callers branch on `code` rather than parse messages."""
from __future__ import annotations

from typing import Any

import httpx


class DropError(Exception):
    """Anything the client raises."""


class NetworkError(DropError):
    """The server could not be reached, or the connection broke."""


class StreamInterrupted(DropError):
    """An event stream closed before the job ended; `stream_events(last_event_id=...)` resumes it."""

    def __init__(self, job_id: str, last_event_id: int | None):
        super().__init__(f"the event stream of job {job_id} closed before the job ended"
                         + (f"; resume after event {last_event_id}" if last_event_id is not None else ""))
        self.job_id, self.last_event_id = job_id, last_event_id


class WaitTimeout(DropError, TimeoutError):
    """`wait` gave up; `job` is the last state seen."""

    def __init__(self, job: dict, timeout: float):
        super().__init__(f"job {job['id']} is still {job['status']} after {timeout:g} s")
        self.job = job


class ApiError(DropError):
    """An error answer: `status`, `code` (stable, e.g. "dataset_in_use"), `detail`, `errors` (the bad fields of a
    422), `problem` (the whole body) and `response`."""

    def __init__(self, response: httpx.Response, problem: dict[str, Any]):
        self.response, self.problem = response, problem
        self.status: int = response.status_code
        self.code: str = problem.get("code") or f"http_{self.status}"
        self.detail: str = problem.get("detail") or response.reason_phrase
        self.errors: list[dict] = problem.get("errors") or []
        super().__init__(f"{self.code}: {self.detail}")


class BadRequest(ApiError):
    """400."""


class Unauthorized(ApiError):
    """401: no token, or an unknown or revoked one."""


class NotFound(ApiError):
    """404: no such object, or another owner's."""


class Conflict(ApiError):
    """409: the object's state forbids it (a finished job, a dataset in use, a policy not ready)."""


class PayloadTooLarge(ApiError):
    """413: over the upload limit or the owner's storage quota."""


class Unprocessable(ApiError):
    """422: invalid input; `errors` names the fields."""


class RateLimited(ApiError):
    """429: over a per-owner limit; `retry_after` is the server's hint in seconds, if it gave one."""

    @property
    def retry_after(self) -> float | None:
        value = self.response.headers.get("retry-after", "")
        return float(value) if value.isdigit() else None


class ServerError(ApiError):
    """5xx."""


_BY_STATUS = {400: BadRequest, 401: Unauthorized, 404: NotFound, 409: Conflict, 413: PayloadTooLarge,
              422: Unprocessable, 429: RateLimited}


def raise_for_problem(response: httpx.Response) -> None:
    """Raise the `ApiError` for an error answer (its body read); do nothing for a success."""
    if response.is_success:
        return
    response.read()
    try:
        body = response.json()
    except ValueError:  # not JSON: a proxy's page, say
        body = None
    problem = body if isinstance(body, dict) else {}
    kind = ServerError if response.status_code >= 500 else _BY_STATUS.get(response.status_code, ApiError)
    raise kind(response, problem)
