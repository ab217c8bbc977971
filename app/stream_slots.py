"""A bound on the event streams one owner holds open in one API process (429 past it).

A stream costs no database connection while it waits, but it holds a socket, a task and memory for as long as its
job runs; the bound keeps one owner from taking them all. It is counted per process: with `drop api --workers N` an
owner may hold up to N times the limit.
"""
from __future__ import annotations

import threading
from collections import Counter
from typing import Callable

from .problems import Problem


class StreamSlots:
    def __init__(self, limit: int):
        self.limit = limit
        self._open: Counter[str] = Counter()
        self._lock = threading.Lock()  # taken in the threadpool, released on the event loop

    def take(self, owner: str) -> Callable[[], None]:
        """A slot for `owner`, or a 429 Problem; call the returned function (idempotent) to give it back."""
        with self._lock:
            if self._open[owner] >= self.limit:
                raise Problem(429, "too_many_streams", f"this owner already has {self.limit} event streams open "
                              "(DROP_MAX_STREAMS_PER_OWNER); close one, or page with ?after=",
                              headers={"Retry-After": "5"})
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

    def held(self) -> int:
        """Streams open in this process, all owners."""
        return sum(self._open.values())
