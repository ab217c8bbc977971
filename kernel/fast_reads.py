"""Single-statement reads for the API's hot endpoints (a job, the job list, a job's events, a dataset, a token),
awaited on the event loop.

A read through a pooled ORM session in the threadpool cost about 520 µs of the API's time on PostgreSQL, the same
query through psycopg's async pool 180 µs, each timed in a loop (bench/NOTES.md). So on PostgreSQL each statement is
compiled once to SQL and runs on the event loop through `psycopg_pool`: no thread hop, no ORM, no pre-ping round
trip. On SQLite (`drop serve`) the same statement runs through SQLAlchemy in the threadpool. Rows come back with
attribute access either way (psycopg's namedtuple rows, SQLAlchemy's `Row`), so serialisers read them as they read ORM
objects.

Statements are built once, at import, with named `bindparam`s, and passed with their values: compiling is cached by
the statement object, so a statement built per request would be compiled per request.
"""
from __future__ import annotations

import asyncio
import logging
from typing import Any, Sequence

import pydantic_core
from sqlalchemy.engine import Engine
from sqlalchemy.sql import Executable

log = logging.getLogger("drop.api")
POOL_WAIT_S = 10.0  # a read that waits this long for a connection fails (500) rather than queueing without end


async def _parse_json_fast(conn) -> None:
    """json and jsonb columns (a job's config and metrics) parsed by pydantic-core: 7 µs for a config that took the
    standard library's parser 17."""
    from psycopg.types.json import set_json_loads

    set_json_loads(pydantic_core.from_json, conn)


class FastReads:
    """The API process's executor of hot reads: open() at startup, close() at shutdown."""

    def __init__(self, engine: Engine, size: int):
        self.engine = engine.execution_options(isolation_level="AUTOCOMMIT")  # SQLite: one statement, no BEGIN
        self.size = size
        self._compiled: dict[int, tuple[Executable, str]] = {}  # id -> (the statement, kept alive; its SQL)
        self._pool = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lost: tuple[type[Exception], ...] = ()
        self._pool_errors: tuple[type[Exception], ...] = ()

    @property
    def on_postgresql(self) -> bool:
        return self.engine.dialect.name == "postgresql"

    async def open(self) -> None:
        """Open the pool on this event loop. A pool serves only the loop that opened it: another lifespan of the same
        app (tests run several clients, each with a loop of its own, on one app) leaves it as it is, and reads from
        any other loop take the threadpool path."""
        if not self.on_postgresql or self._pool is not None:
            return
        from psycopg import OperationalError
        from psycopg.rows import namedtuple_row
        from psycopg_pool import AsyncConnectionPool, PoolClosed, PoolTimeout, TooManyRequests

        self._lost, self._pool_errors = (OperationalError,), (PoolClosed, PoolTimeout, TooManyRequests)
        self._loop = asyncio.get_running_loop()
        conninfo = self.engine.url.set(drivername="postgresql").render_as_string(hide_password=False)
        self._pool = AsyncConnectionPool(conninfo, min_size=1, max_size=self.size, open=False, timeout=POOL_WAIT_S,
                                         kwargs={"autocommit": True, "row_factory": namedtuple_row},
                                         configure=_parse_json_fast)
        await self._pool.open()

    async def close(self) -> None:
        if self._pool is not None and asyncio.get_running_loop() is self._loop:
            pool, self._pool = self._pool, None
            await pool.close()

    async def all(self, stmt: Executable, **params: Any) -> Sequence[Any]:
        """Every row of `stmt` with its bind parameters `params`."""
        if self._pool is None or asyncio.get_running_loop() is not self._loop:
            return await asyncio.to_thread(self._sync, stmt, params)
        sql = self._sql(stmt)
        try:
            return await self._fetch(sql, params)
        except self._lost as exc:  # the server closed connections (a restart): drop the dead ones, ask again
            if isinstance(exc, self._pool_errors):  # a full or closed pool is not a lost connection
                raise
            log.warning("read retried after a lost database connection: %s", exc)
            await self._pool.check()
            return await self._fetch(sql, params)

    async def _fetch(self, sql: str, params: dict[str, Any]) -> list[Any]:
        async with self._pool.connection() as conn:
            return await (await conn.execute(sql, params)).fetchall()

    async def one(self, stmt: Executable, **params: Any) -> Any | None:
        """The first row of `stmt`, or None."""
        rows = await self.all(stmt, **params)
        return rows[0] if rows else None

    def _sql(self, stmt: Executable) -> str:
        found = self._compiled.get(id(stmt))
        if found is None:
            compiled = stmt.compile(dialect=self.engine.dialect)
            # Only named bind parameters, all given per call: a literal or an IN list would need values compiled in.
            if compiled.params.keys() - {b.key for b in compiled.binds.values() if b.value is None} or \
                    "POSTCOMPILE" in str(compiled):
                raise ValueError(f"a fast read takes named bindparams only: {compiled}")
            found = self._compiled[id(stmt)] = (stmt, str(compiled))
        return found[1]

    def _sync(self, stmt: Executable, params: dict[str, Any]) -> Sequence[Any]:
        with self.engine.connect() as conn:
            return conn.execute(stmt, params).all()
