"""Wake a job's event streams as soon as the job has a new event, instead of each stream polling the database.

On PostgreSQL a trigger (migration 0003) sends `NOTIFY drop_job_events, '<job id>'` when an event row commits, from
whichever process wrote it (a worker, the reaper, the API). Each API process holds one LISTEN connection, outside the
request pool, and wakes the streams of that job. Streams keep a slow safety poll (the keep-alive interval), and poll
at the fast interval whenever the listener is down or the database is SQLite, which has no notifications.
"""
from __future__ import annotations

import asyncio
import itertools
import logging
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from typing import Awaitable, Callable, Hashable, Iterator, TypeVar

log = logging.getLogger("drop.api")
CHANNEL = "drop_job_events"
RECONNECT_S = 2.0
T = TypeVar("T")
_serials = itertools.count()


class SharedReads:
    """Identical reads in flight at once share one. A job's streams wake together on its notification, all at the same
    cursor, and each asked the database the same two questions: 100 streams made 200 queries per event, and the
    polls waited behind them (bench/results/service_load.md). A stream keys its read by the notification version it
    saw before reading (and its topic's serial), so it never joins a read that started before a notification it has
    already seen."""

    def __init__(self) -> None:
        self._flights: dict[Hashable, list] = {}  # key -> [the read's task, how many wait for it]

    async def run(self, key: Hashable, read: Callable[[], Awaitable[T]]) -> T:
        flight = self._flights.get(key)
        if flight is None:
            task = asyncio.ensure_future(read())
            flight = self._flights[key] = [task, 0]
            task.add_done_callback(lambda done: self._landed(key, done))
        flight[1] += 1
        try:
            return await asyncio.shield(flight[0])  # one waiter leaving (its client went) leaves the others' read
        finally:
            flight[1] -= 1
            if not flight[1] and not flight[0].done():  # the last one left: nobody needs the read
                flight[0].cancel()

    def _landed(self, key: Hashable, task: asyncio.Future) -> None:
        if self._flights.get(key, [None])[0] is task:
            del self._flights[key]
        if not task.cancelled():
            task.exception()  # retrieved here: each waiter got it already


@dataclass
class Topic:
    """One job's waiters: `version` counts notifications, so a waiter that saw version v before querying the database
    returns at once if one arrived in between."""
    version: int = 0
    event: asyncio.Event = field(default_factory=asyncio.Event)
    refs: int = 0
    # Topics come and go with their streams, and a new one's version starts again at 0: reads are keyed by both.
    serial: int = field(default_factory=lambda: next(_serials))


class EventWaker:
    """In-process fan-out of "job X has new events" to the streams following X."""

    def __init__(self) -> None:
        self.live = False  # a listener is connected: notifications arrive
        self._topics: dict[str, Topic] = {}

    @contextmanager
    def subscribe(self, job_id: str) -> Iterator[Topic]:
        topic = self._topics.setdefault(job_id, Topic())
        topic.refs += 1
        try:
            yield topic
        finally:
            topic.refs -= 1
            if not topic.refs:
                del self._topics[job_id]

    def notify(self, job_id: str) -> None:
        topic = self._topics.get(job_id)
        if topic is not None:
            topic.version += 1
            topic.event.set()
            topic.event = asyncio.Event()

    def notify_all(self) -> None:
        for job_id in list(self._topics):
            self.notify(job_id)

    @staticmethod
    async def wait(topic: Topic, seen: int, timeout: float) -> None:
        """Until a notification newer than `seen`, or `timeout` seconds."""
        if topic.version == seen:
            with suppress(asyncio.TimeoutError):
                await asyncio.wait_for(topic.event.wait(), timeout)


async def listen(conninfo: str, waker: EventWaker) -> None:
    """LISTEN until cancelled, reconnecting after a lost connection; every stream is woken on (re)connect, for what
    may have been missed meanwhile."""
    import psycopg

    while True:
        try:
            async with await psycopg.AsyncConnection.connect(conninfo, autocommit=True) as conn:
                await conn.execute(f"LISTEN {CHANNEL}")
                waker.live = True
                waker.notify_all()
                async for note in conn.notifies():
                    waker.notify(note.payload)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            log.warning("event listener lost its connection (%s); streams poll until it is back",
                        type(exc).__name__)
        finally:
            waker.live = False
        await asyncio.sleep(RECONNECT_S)
