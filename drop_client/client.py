"""`DropClient`: the drop-rl REST API from Python, on httpx, with the event stream read by httpx-sse."""
from __future__ import annotations

import sys
import time
from email.message import Message
from pathlib import Path
from typing import Any, Callable, Iterator, Literal, TextIO

import httpx
from httpx_sse import EventSource, SSEError

from .errors import DropError, NetworkError, StreamInterrupted, WaitTimeout, raise_for_problem

DEFAULT_SERVER = "http://127.0.0.1:8000"
FINISHED = frozenset({"succeeded", "failed", "cancelled"})
Which = Literal["last", "best"]
PolicyFormat = Literal["torchscript", "onnx", "state_dict", "metadata"]
JobStatus = Literal["queued", "running", "cancelling", "succeeded", "failed", "cancelled"]


class DropClient:
    """One server, one owner's bearer token (none for `drop serve`, whose auth is off). `http` replaces the
    connection, e.g. to set pool limits or to talk to an app in-process through a TestClient."""

    def __init__(self, server: str = DEFAULT_SERVER, token: str | None = None, *, timeout: float = 60.0,
                 http: httpx.Client | None = None):
        self._owned = http is None
        self.http = http if http is not None else httpx.Client(base_url=server, timeout=timeout)
        self._auth = {"Authorization": f"Bearer {token}"} if token else {}
        # An upload's answer waits for its validation (minutes for a large file): no read timeout, unless `http`
        # brought timeouts of its own.
        self._upload_timeout = httpx.Timeout(timeout, read=None) if self._owned else httpx.USE_CLIENT_DEFAULT

    def close(self) -> None:
        if self._owned:
            self.http.close()

    def __enter__(self) -> DropClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _request(self, method: str, path: str, *, headers: dict | None = None, **kw) -> httpx.Response:
        try:
            response = self.http.request(method, path, headers={**self._auth, **(headers or {})}, **kw)
        except httpx.TransportError as exc:
            raise NetworkError(f"{method} {self.http.base_url.join(path)}: {exc or type(exc).__name__}") from exc
        raise_for_problem(response)
        return response

    def _pages(self, path: str, params: dict) -> Iterator[dict]:
        """Every item of a cursor-paged list, fetching the next page when the last one is used up."""
        after = None
        while True:
            page = self._request("GET", path, params={**params, **_given(after=after)}).json()
            yield from page["data"]
            if not page["has_more"]:
                return
            after = page["next_after"]

    # Datasets

    def upload_dataset(self, path: str | Path, *, name: str | None = None) -> dict:
        """Upload a D4RL-layout .hdf5 or .npz, or a zipped Minari dataset; the validated dataset with its report."""
        path = Path(path)
        with path.open("rb") as fh:
            return self._request("POST", "/v1/datasets", params=_given(name=name), timeout=self._upload_timeout,
                                 files={"file": (path.name, fh, "application/octet-stream")}).json()

    def list_datasets(self) -> Iterator[dict]:
        """The owner's datasets, newest first."""
        return self._pages("/v1/datasets", {"limit": 100})

    def delete_dataset(self, dataset_id: str) -> None:
        self._request("DELETE", f"/v1/datasets/{dataset_id}")

    # Jobs

    def create_job(self, dataset_id: str, *, algorithm: str | None = None, env: str | None = None,
                   preset: str | None = None, task: str | None = None, seed: int | None = None,
                   overrides: dict[str, Any] | None = None, max_runtime_s: int | None = None,
                   idempotency_key: str | None = None) -> dict:
        """Queue a training job; what is left out takes the server's default. Sending the same `idempotency_key`
        again returns the job the first request made."""
        body = _given(dataset_id=dataset_id, algorithm=algorithm, env=env, preset=preset, task=task, seed=seed,
                      overrides=overrides, max_runtime_s=max_runtime_s)
        headers = _given(**{"Idempotency-Key": idempotency_key})
        return self._request("POST", "/v1/jobs", json=body, headers=headers).json()

    def get_job(self, job_id: str) -> dict:
        return self._request("GET", f"/v1/jobs/{job_id}").json()

    def list_jobs(self, status: str | None = None) -> Iterator[dict]:
        """The owner's jobs, newest first, optionally of one status."""
        return self._pages("/v1/jobs", {"limit": 100, **_given(status=status)})

    def cancel_job(self, job_id: str) -> dict:
        """Cancel a queued job at once or a running one at its next step (it is `cancelling` until then)."""
        return self._request("POST", f"/v1/jobs/{job_id}/cancel").json()

    def delete_job(self, job_id: str) -> None:
        """Delete a finished job with its checkpoints, policies and records; refused (409) until it has finished."""
        self._request("DELETE", f"/v1/jobs/{job_id}")

    def list_events(self, job_id: str, after: int = 0) -> Iterator[dict]:
        """The job's events so far after event `after`, oldest first."""
        return self._pages(f"/v1/jobs/{job_id}/events", {"limit": 1000, **_given(after=after or None)})

    def list_evaluations(self, job_id: str) -> list[dict]:
        """The job's evaluations in the real env so far: epoch, mean return, D4RL normalised score."""
        return list(self._pages(f"/v1/jobs/{job_id}/evaluations", {}))

    def stream_events(self, job_id: str, last_event_id: int | None = None) -> Iterator[dict]:
        """The job's events after `last_event_id` (all when None) as they happen, until the job ends. Raises
        `StreamInterrupted`, naming the last event received, if the connection ends first."""
        headers = {**self._auth, "Accept": "text/event-stream",
                   **_given(**{"Last-Event-ID": None if last_event_id is None else str(last_event_id)})}
        try:
            with self.http.stream("GET", f"/v1/jobs/{job_id}/events", headers=headers) as response:
                raise_for_problem(response)
                for sse in EventSource(response).iter_sse():
                    if sse.event == "end":
                        return
                    if not sse.data:  # the keep-alive comment: httpx-sse reports it as an empty event
                        continue
                    event = sse.json()
                    last_event_id = event["id"]
                    yield event
        except httpx.TransportError as exc:
            raise StreamInterrupted(job_id, last_event_id) from exc
        except SSEError as exc:  # not an event stream: not this API, or a proxy in the way
            raise DropError(f"job {job_id}'s events: {exc}") from exc
        raise StreamInterrupted(job_id, last_event_id)

    def wait(self, job_id: str, *, until: Callable[[dict], bool] | None = None, timeout: float | None = None,
             poll_s: float = 0.5, progress: Callable[[dict], None] | None = None) -> dict:
        """Poll the job until it has finished, or until `until(job)` holds, and return it. `progress(job)` is
        called whenever its status or progress changes (`print_progress` prints a line). Polling, unlike a stream,
        carries on across a restart of the API."""
        deadline = None if timeout is None else time.monotonic() + timeout
        shown = None
        while True:
            job = self.get_job(job_id)
            if progress is not None and (job["status"], job["progress"]) != shown:
                shown = job["status"], job["progress"]
                progress(job)
            if job["status"] in FINISHED or (until is not None and until(job)):
                return job
            if deadline is not None and time.monotonic() >= deadline:
                raise WaitTimeout(job, timeout)
            time.sleep(poll_s)

    def download_policy(self, job_id: str, path: str | Path = ".", *, which: Which = "last",
                        format: PolicyFormat = "torchscript") -> Path:
        """Save a succeeded job's policy (`last`: after the final epoch; `best`: of its best evaluation) to `path`,
        a file or an existing directory (then named as the server names it); return the file's path."""
        path = Path(path)
        try:
            with self.http.stream("GET", f"/v1/jobs/{job_id}/policy", params={"which": which, "format": format},
                                  headers=self._auth) as response:
                raise_for_problem(response)
                if path.is_dir():
                    path = path / _filename(response, f"{job_id}-{which}-policy")
                part = path.with_name(path.name + ".part")
                try:
                    with part.open("wb") as out:
                        for chunk in response.iter_bytes():
                            out.write(chunk)
                    part.replace(path)
                finally:
                    part.unlink(missing_ok=True)
        except httpx.TransportError as exc:
            raise NetworkError(f"downloading the policy of job {job_id}: {exc or type(exc).__name__}") from exc
        return path


def print_progress(job: dict, file: TextIO | None = None) -> None:
    """A `wait` progress callback: one line per change, e.g. `job_1: running, train epoch 3 (40%)`."""
    parts = [f"{job['id']}: {job['status']}"]
    if job["status"] == "running" and (p := job["progress"]):
        parts.append(f"train epoch {p['epoch']} ({p['fraction']:.0%})" if p["phase"] == "train"
                     else f"{p['phase']} {p['step']}" + (f"/{p['total']}" if p["total"] else ""))
    if job["last_score"] is not None and job["best_score"] is not None:
        parts.append(f"last score {job['last_score']:.1f}, best {job['best_score']:.1f}")
    if job["error"]:
        parts.append(f"{job['error']['code']}: {job['error']['message']}")
    print(", ".join(parts), file=file or sys.stderr, flush=True)


def _given(**values) -> dict:
    """The arguments that were given (not None), for a query, body or headers."""
    return {k: v for k, v in values.items() if v is not None}


def _filename(response: httpx.Response, fallback: str) -> str:
    """The file name the server suggests in Content-Disposition, without any folder part."""
    message = Message()
    message["content-disposition"] = response.headers.get("content-disposition", "")
    return Path(message.get_filename() or fallback).name or fallback

