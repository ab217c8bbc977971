"""Bounds on what requests hold open in one API process: event streams per owner, and uploads per owner and in all
(429 with Retry-After past a bound).

A slot costs no database connection, but it holds a socket, a task and memory for as long as it lasts (an upload also
a file, then a place in the validator's queue); the bounds keep one owner, or all of them together, from taking them
all. They are counted per process, as the file descriptors and memory they protect are: with `drop api --workers N`
the totals are N times these.
"""
from __future__ import annotations

import threading
from collections import Counter
from contextlib import contextmanager
from typing import Callable, Iterator, Literal

from kernel.settings import Settings

from .problems import Problem

Bound = Literal["owner", "total"]
UPLOAD_RETRY_AFTER_S = 10  # an upload and its validation take seconds to minutes


class Slots:
    def __init__(self, per_owner: int, refuse: Callable[[Bound], Problem], total: int | None = None):
        self.per_owner, self.total, self.refuse = per_owner, total, refuse
        self._open: Counter[str] = Counter()
        self._lock = threading.Lock()  # taken in the threadpool and on the event loop

    def take(self, owner: str) -> Callable[[], None]:
        """A slot for `owner`, or the 429 Problem of the bound it would pass; call the returned function (idempotent)
        to give it back."""
        with self._lock:
            if self._open[owner] >= self.per_owner:
                raise self.refuse("owner")
            if self.total is not None and sum(self._open.values()) >= self.total:
                raise self.refuse("total")
            self._open[owner] += 1
        released = False

        def release() -> None:
            nonlocal released
            with self._lock:
                if not released:
                    released = True
                    self._open[owner] -= 1
                    if not self._open[owner]:
                        del self._open[owner]

        return release

    @contextmanager
    def hold(self, owner: str) -> Iterator[None]:
        release = self.take(owner)
        try:
            yield
        finally:
            release()

    def held(self) -> int:
        """Slots held in this process, all owners."""
        with self._lock:
            return sum(self._open.values())


def stream_slots(settings: Settings) -> Slots:
    limit = settings.max_streams_per_owner
    return Slots(limit, lambda _: Problem(
        429, "too_many_streams", f"this owner already has {limit} event streams open (DROP_MAX_STREAMS_PER_OWNER); "
        "close one, or page with ?after=", headers={"Retry-After": "5"}))


def upload_slots(settings: Settings) -> Slots:
    """Uploads in progress, from the first body byte to the end of validation."""
    per_owner, total = settings.max_uploads_per_owner, settings.max_concurrent_uploads

    def refuse(bound: Bound) -> Problem:
        if bound == "owner":
            detail = (f"you already have {per_owner} uploads in progress (DROP_MAX_UPLOADS_PER_OWNER); wait for one "
                      "to finish")
        else:
            detail = f"the server already has {total} uploads in progress (DROP_MAX_CONCURRENT_UPLOADS); try again"
        return Problem(429, "too_many_uploads", detail, headers={"Retry-After": str(UPLOAD_RETRY_AFTER_S)})

    return Slots(per_owner, refuse, total)

