"""The hot reads' executor (kernel/fast_reads.py): on PostgreSQL its compiled statements answer what the ORM reads
would, JSON, timestamps and NULLs included, for every variant of the job list; a read survives the server dropping the
pool's connections; and on SQLite the same statements run through SQLAlchemy."""
from __future__ import annotations

import asyncio
import json
from datetime import datetime, timezone

import orjson
import psycopg
import pytest
from sqlalchemy import bindparam, func, select
from sqlalchemy.engine import make_url

from app.core.fast_json import FastJSONResponse
from app.core.problems import Problem
from app.jobs import reads, schemas
from kernel import fast_reads
from kernel.db import make_engine, make_sessionmaker
from kernel.fast_reads import FastReads
from kernel.ids import new_id
from kernel.job_state import JobStatus
from kernel.models import Job, JobEvent

from .backends import PG_ADMIN, migrated_engine

OWNER = "own_fast"


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def db(request, tmp_path_factory):
    """(engine, ORM sessions, the ids of three jobs, newest last) on a migrated database of the module's own."""
    with migrated_engine(request.param, tmp_path_factory.mktemp("fast-reads"), OWNER) as engine:
        sessions = make_sessionmaker(engine)
        ids = [new_id("job") for _ in range(3)]
        with sessions.begin() as s:
            for i, job_id in enumerate(ids):
                s.add(Job(id=job_id, owner_id=OWNER, algorithm="drop", env="hopper", preset="smoke",
                          overrides={"epochs": i, "sac": {"hidden": [64, 64]}}, seed=i, config={"nested": [1, 2.5]},
                          status=("queued", "running", "succeeded")[i], attempts=i, max_attempts=3,
                          max_runtime_s=600, progress={"epoch": i} if i else None, best_score=i and 1.5 * i,
                          error_code="x" if i == 2 else None, error_message="boom" if i == 2 else None,
                          started_at=datetime(2026, 1, 2, 3, 4, 5, 678000, tzinfo=timezone.utc) if i else None))
                s.flush()
                s.add(JobEvent(job_id=job_id, type="status", message=f"event {i}", data={"i": i}))
        yield engine, sessions, ids


def received(content):
    """What a client receives for `content`: JSON columns the hot reads pass through unparsed read back as values."""
    return json.loads(FastJSONResponse(content).body)


def run(coroutine_fn):
    """Run `coroutine_fn(fast_reads)` on a fresh event loop with an open executor."""
    async def body(engine):
        fast = FastReads(engine, 2)
        await fast.open()
        try:
            return await coroutine_fn(fast)
        finally:
            await fast.close()
    return body


def test_job_matches_the_orm_read(db):
    engine, sessions, ids = db
    for job_id in ids:
        with sessions() as s:
            expected = schemas.job(s.get(Job, job_id))
        got = asyncio.run(run(lambda fast, j=job_id: reads.job(fast, OWNER, j))(engine))
        if engine.dialect.name == "postgresql":  # stored JSON is never parsed on the way through
            assert all(isinstance(got[k], orjson.Fragment) for k in ("config", "overrides", "progress"))
        got = received(got)
        assert got == expected
    assert got["started_at"] == "2026-01-02T03:04:05.678000Z" and got["error"] == {"code": "x", "message": "boom"}


def test_concurrent_job_reads_share_one_statement(db):
    """Job reads that start together are one statement, sent once; each gets its own job, a foreign owner a 404."""
    engine, sessions, ids = db
    with sessions() as s:
        expected = {job_id: schemas.job(s.get(Job, job_id)) for job_id in ids}

    async def body(fast):
        sent = []
        real = fast.all

        async def counted(stmt, **params):
            sent.append(sorted(params["keys"]))
            return await real(stmt, **params)
        fast.all = counted
        reads_ = [reads.job(fast, OWNER, j) for j in (*ids, ids[0])] + [reads.job(fast, "someone_else", ids[1])]
        return sent, await asyncio.gather(*reads_, return_exceptions=True)

    sent, got = asyncio.run(run(body)(engine))
    assert sent == [sorted(ids)]
    assert [received(g) for g in got[:4]] == [expected[j] for j in (*ids, ids[0])]
    assert isinstance(got[4], Problem) and got[4].status == 404


def test_a_read_after_a_sent_batch_sees_a_later_write(db):
    """A read never joins a batch already sent: a write committed before the read began is in its answer."""
    engine, sessions, ids = db

    async def body(fast):
        queried, release = asyncio.Event(), asyncio.Event()
        real = fast.all

        async def held(stmt, **params):  # the reads have their rows but do not answer yet
            rows = await real(stmt, **params)
            if params["keys"] == [ids[1]]:
                queried.set()
            await release.wait()
            return rows
        fast.all = held
        first = asyncio.ensure_future(reads.job(fast, OWNER, ids[0]))  # its batch sent on the next turn
        await asyncio.sleep(0)
        early = asyncio.ensure_future(reads.job(fast, OWNER, ids[1]))  # a batch, sent and read
        await queried.wait()
        with sessions.begin() as s:
            s.get(Job, ids[1]).attempts = 7
        late = asyncio.ensure_future(reads.job(fast, OWNER, ids[1]))
        await asyncio.sleep(0)
        release.set()
        await first
        return await early, await late

    try:
        early, late = asyncio.run(run(body)(engine))
        assert (early["attempts"], late["attempts"]) == (1, 7)
    finally:
        with sessions.begin() as s:
            s.get(Job, ids[1]).attempts = 1


def test_a_failed_batch_fails_every_read_in_it(db):
    """Every read of a batch answers with the statement's error."""
    engine, _, ids = db

    async def body(fast):
        async def broken(stmt, **params):
            raise RuntimeError("database gone")
        fast.all = broken
        return await asyncio.gather(*(reads.job(fast, OWNER, j) for j in ids), return_exceptions=True)

    assert [str(e) for e in asyncio.run(run(body)(engine))] == ["database gone"] * 3


@pytest.mark.parametrize("status", [None, JobStatus.RUNNING])
@pytest.mark.parametrize("after", [False, True])
def test_every_job_list_variant(db, status, after):
    engine, sessions, ids = db
    cursor = ids[-1] if after else None
    with sessions() as s:
        q = select(Job).where(Job.owner_id == OWNER).order_by(Job.id.desc())
        rows = [r for r in s.scalars(q) if (status is None or r.status == status.value)
                and (cursor is None or r.id < cursor)]
        expected = [schemas.job(r) for r in rows]
    page = asyncio.run(run(lambda fast: reads.jobs_page(fast, OWNER, status, cursor, 1))(engine))
    assert received(page["data"]) == expected[:1] and page["has_more"] == (len(expected) > 1)


def test_unknown_and_foreign_jobs_are_404_and_events_page(db):
    engine, _, ids = db

    async def body(fast):
        for owner, job_id in (("someone_else", ids[0]), (OWNER, new_id("job")), (OWNER, "not-an-id")):
            for read in (reads.job(fast, owner, job_id), reads.events_page(fast, owner, job_id, 0, 10)):
                with pytest.raises(Problem) as caught:
                    await read
                assert caught.value.status == 404
        return [await reads.events_page(fast, OWNER, ids[1], after, 10) for after in (0, 10**6)]

    events, none_after = map(received, asyncio.run(run(body)(engine)))
    assert [e["message"] for e in events["data"]] == ["event 1"] and events["data"][0]["data"] == {"i": 1}
    assert none_after == {"object": "list", "data": [], "has_more": False, "next_after": None}


def test_events_pages_walk_every_event_in_order(db):
    """The page is cut before the join with the owner's job: each page continues where the last ended."""
    engine, sessions, ids = db
    with sessions.begin() as s:
        s.add_all(JobEvent(job_id=ids[2], type="progress", message=f"more {i}") for i in range(24))

    async def body(fast):
        pages, after = [], 0
        while after is not None:
            pages.append(await reads.events_page(fast, OWNER, ids[2], after, 10))
            after = pages[-1]["next_after"]
        return pages

    pages = asyncio.run(run(body)(engine))
    assert [(len(p["data"]), p["has_more"]) for p in pages] == [(10, True), (10, True), (5, False)]
    messages = [e["message"] for p in pages for e in p["data"]]
    assert messages == ["event 2"] + [f"more {i}" for i in range(24)]


def test_a_read_survives_the_server_dropping_its_connections(db):
    engine, _, ids = db
    if engine.dialect.name != "postgresql":
        pytest.skip("a PostgreSQL connection pool")

    async def body(fast):
        first = await reads.job(fast, OWNER, ids[0])
        with psycopg.connect(PG_ADMIN, autocommit=True) as admin:  # what a server restart does to the pool
            killed = admin.execute("SELECT count(pg_terminate_backend(pid)) FROM pg_stat_activity "
                                   "WHERE datname = %s AND pid <> pg_backend_pid()", (engine.url.database,)).fetchone()
        assert killed[0] >= 2  # both of the pool's connections, opened at start: the retry finds no live one
        return first, [await reads.job(fast, OWNER, ids[0]) for _ in range(2)]

    first, again = asyncio.run(run(body)(engine))
    assert [received(a) for a in again] == [received(first)] * 2


def test_a_database_url_with_libpq_options_opens_the_pool(db):
    """Options of the URL that psycopg reads and asyncpg does not (connect_timeout, keepalives) stay off the hot reads'
    connections, where the server would refuse them as unknown settings and the API would not start; a server setting
    in the URL (application_name) still reaches the server."""
    engine, _, ids = db
    if engine.dialect.name != "postgresql":
        pytest.skip("a PostgreSQL connection pool")
    url = engine.url.update_query_dict({"connect_timeout": "5", "keepalives": "1", "application_name": "drop_fast"})
    with_options = make_engine(url.render_as_string(hide_password=False))
    try:
        async def body(fast):
            name = await fast.all(select(func.current_setting(bindparam("name"))), name="application_name")
            return name, await reads.job(fast, OWNER, ids[0])

        name, job = asyncio.run(run(body)(with_options))
    finally:
        with_options.dispose()
    assert [tuple(row) for row in name] == [("drop_fast",)] and job["id"] == ids[0]
    assert fast_reads.asyncpg_connect_args(url)[1] == {"timeout": 5.0}


def test_connect_timeout_named_twice_or_malformed():
    """libpq takes the last of a repeated keyword; a timeout that is not a number is refused by name."""
    twice = make_url("postgresql+psycopg://u@h/db?connect_timeout=5&connect_timeout=7")
    assert fast_reads.asyncpg_connect_args(twice)[1] == {"timeout": 7.0}
    with pytest.raises(ValueError, match="connect_timeout .* not 'soon'"):
        fast_reads.asyncpg_connect_args(make_url("postgresql+psycopg://u@h/db?connect_timeout=soon"))


def test_a_read_that_finds_no_free_connection_times_out_and_keeps_the_pool(db, monkeypatch, caplog):
    """Waiting past POOL_WAIT_S is a TimeoutError (a 500), not a lost connection: the busy connection is not dropped."""
    engine, _, ids = db
    if engine.dialect.name != "postgresql":
        pytest.skip("a PostgreSQL connection pool")
    monkeypatch.setattr(fast_reads, "POOL_WAIT_S", 0.2)
    sleep = select(func.pg_sleep(bindparam("seconds")))

    async def body():
        fast = FastReads(engine, 1)
        await fast.open()
        try:
            (busy,) = [c for c in fast._pool._slots._queue]
            held = asyncio.ensure_future(fast.all(sleep, seconds=1.0))
            await asyncio.sleep(0.05)
            with pytest.raises(TimeoutError):
                await reads.job(fast, OWNER, ids[0])
            await held
            (after,) = [c for c in fast._pool._slots._queue]
            return busy, after, after.is_closed(), await reads.job(fast, OWNER, ids[0])
        finally:
            await fast.close()

    busy, after, closed, job = asyncio.run(body())
    assert after is busy and not closed and job["id"] == ids[0]
    assert "lost database connection" not in caplog.text  # no retry, no renewal


def test_a_second_event_loop_reads_without_the_first_ones_pool(db):
    """Two lifespans of one app (two test clients, each with its own loop): the pool stays the first loop's, the
    second reads through the threadpool, and only the first one's close closes it."""
    engine, _, ids = db
    fast = FastReads(engine, 2)

    async def first_open():
        await fast.open()
        return fast._pool

    other = asyncio.new_event_loop()
    try:
        pool = other.run_until_complete(first_open())
        assert asyncio.run(reads.job(fast, OWNER, ids[0]))["id"] == ids[0]  # another loop: no cross-loop pool use

        async def second_lifespan():
            await fast.open()
            await fast.close()
        asyncio.run(second_lifespan())
        assert fast._pool is pool
        other.run_until_complete(fast.close())
        assert fast._pool is None and (pool is None or pool.closed)
    finally:
        other.close()


def test_fast_json_bodies_read_back_as_written():
    """The hot reads' bodies (orjson, pydantic-core for what orjson refuses) parse to what they were made from; NaN
    and infinities are null, not a 500."""
    content = {"ü": "ünï \u2028 \"q\"", "n": [1, 2.5, 1e300, -0.0, None, True], "deep": {"a": {"b": []}}, "big": 2**70}
    assert json.loads(FastJSONResponse(content).body) == content  # the big integer: pydantic-core's path
    del content["big"]
    assert json.loads(FastJSONResponse(content).body) == content  # orjson's
    assert json.loads(FastJSONResponse({"x": float("nan"), "y": [float("-inf")]}).body) == {"x": None, "y": [None]}
