"""SharedReads (app/jobs/event_bus.py): the streams of one job that read at once with the same key make one query
between them; another key, or a read after the first has finished, queries again; a waiter that leaves does not
cancel the read the others wait for; an error reaches every waiter."""
from __future__ import annotations

import asyncio

import pytest

from app.jobs.event_bus import SharedReads


class Database:
    def __init__(self) -> None:
        self.queries: list[str] = []
        self.gate = asyncio.Event()

    async def read(self, key: str) -> list[str]:
        self.queries.append(key)
        await self.gate.wait()
        if key == "broken":
            raise RuntimeError("lost connection")
        return [f"rows of {key}"]


def test_concurrent_identical_reads_share_one_query():
    async def body():
        shared, db = SharedReads(), Database()
        same = [asyncio.create_task(shared.run(("job", 5, 0), lambda: db.read("a"))) for _ in range(100)]
        other = asyncio.create_task(shared.run(("job", 5, 1), lambda: db.read("b")))
        await asyncio.sleep(0)
        same[0].cancel()  # one client leaves while the read is in flight
        db.gate.set()
        results = await asyncio.gather(*same[1:], other)
        assert db.queries == ["a", "b"]
        assert results == [["rows of a"]] * 99 + [["rows of b"]]
        assert same[0].cancelled()
        assert await shared.run(("job", 5, 0), lambda: db.read("a")) == ["rows of a"]  # finished: asks again
        assert db.queries == ["a", "b", "a"]

    asyncio.run(body())


def test_a_read_nobody_waits_for_is_cancelled():
    """Every stream left (their clients went): the read stops too, rather than outliving them and their loop."""
    async def body():
        shared, db = SharedReads(), Database()
        waiters = [asyncio.create_task(shared.run("k", lambda: db.read("a"))) for _ in range(2)]
        await asyncio.sleep(0)
        flight = next(iter(shared._flights.values()))[0]
        for waiter in waiters:
            waiter.cancel()
        await asyncio.gather(*waiters, return_exceptions=True)
        await asyncio.sleep(0)
        assert flight.cancelled() and not shared._flights

    asyncio.run(body())


def test_an_error_reaches_every_waiter():
    async def body():
        shared, db = SharedReads(), Database()
        waiters = [asyncio.create_task(shared.run("k", lambda: db.read("broken"))) for _ in range(3)]
        await asyncio.sleep(0)
        db.gate.set()
        for waiter in waiters:
            with pytest.raises(RuntimeError, match="lost connection"):
                await waiter
        assert db.queries == ["broken"]

    asyncio.run(body())
