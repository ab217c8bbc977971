"""Single-statement reads for the API's hot endpoints (a job, the job list, a job's events, a dataset, a token),
awaited on the event loop.

On PostgreSQL each statement is compiled once to SQL and runs on the event loop over asyncpg connections: no thread
hop, no ORM, no pre-ping round trip. Timed in a loop on a job read (bench/NOTES.md): an ORM session in the threadpool
cost the API about 520 µs, psycopg's async pool 227, asyncpg's own pool 305 (140 without its reset on release), a
queue of asyncpg connections 91. asyncpg's pool also runs its acquire with a timeout and its release each in a task
of their own (asyncio.wait_for on Python 3.11, asyncio.shield): two more turns of the event loop per read, which under
load doubled the p99 of bench/service_load.py's fixed load. So `_Connections` below is the pool: a LIFO of idle
connections, all opened at start, with no reset (these connections run single autocommit SELECTs and never change
their session).

On SQLite (`drop serve`) the same statements run through SQLAlchemy in the threadpool. Rows come back with attribute
access either way (SQLAlchemy's `Row`, `Row` below), so serialisers read them as they read ORM objects.

Statements are built once, at import, with named `bindparam`s, and passed with their values: compiling is cached by
the statement object, so a statement built per request would be compiled per request.
"""
from __future__ import annotations

import asyncio
import logging
from typing import Any, Sequence

import orjson
from sqlalchemy.engine import URL, Engine
from sqlalchemy.sql import Executable

log = logging.getLogger("drop.api")
POOL_WAIT_S = 10.0  # a read that waits this long for a connection fails (TimeoutError, a 500), not queueing on
BATCH_MAX = 100  # keys in one batched read
# libpq's connection keywords (PostgreSQL 17's list) that asyncpg's DSN does not read. asyncpg sends any query option
# it does not know to the server as a run-time setting, and the server then refuses the connection ("unrecognized
# configuration parameter"): a database URL that psycopg, the ORM's driver, accepts would stop the API at startup.
# They shape psycopg's client side; the hot reads' connections go without them, connect_timeout as asyncpg's timeout.
LIBPQ_ONLY = frozenset({
    "hostaddr", "require_auth", "channel_binding", "connect_timeout", "fallback_application_name", "keepalives",
    "keepalives_idle", "keepalives_interval", "keepalives_count", "tcp_user_timeout", "replication", "gssencmode",
    "requiressl", "sslcompression", "sslcertmode", "sslcrldir", "sslsni", "requirepeer", "gssdelegation",
    "load_balance_hosts",
})


def asyncpg_connect_args(url: URL) -> tuple[str, dict[str, Any]]:
    """The DSN and keyword arguments of `asyncpg.connect` for the database at SQLAlchemy `url`."""
    query = dict(url.query)
    dsn = url.set(drivername="postgresql", query={k: v for k, v in query.items() if k not in LIBPQ_ONLY})
    given = query.get("connect_timeout") or 0  # make_engine's URL always names one (kernel.db.with_connect_timeout)
    if isinstance(given, tuple):  # named twice: libpq takes the last
        given = given[-1]
    try:
        timeout = float(given)  # 0: asyncpg keeps its default, 60 s
    except ValueError:
        raise ValueError(f"connect_timeout in the database URL must be seconds, not {given!r}") from None
    return dsn.render_as_string(hide_password=False), ({"timeout": timeout} if timeout > 0 else {})


class _Batch:
    def __init__(self, loop: asyncio.AbstractEventLoop):
        self.loop, self.keys = loop, set()
        self.rows: asyncio.Task | None = None  # the read of them all, which starts on the loop's next turn


def _row_class():
    import asyncpg

    class Row(asyncpg.Record):
        """A record whose columns read as attributes, as SQLAlchemy's rows do."""

        def __getattr__(self, name: str) -> Any:
            try:
                return self[name]
            except KeyError:
                raise AttributeError(name) from None

    return Row


async def _setup(conn) -> None:
    """json and jsonb columns (a job's config and metrics, a dataset's report) come back unparsed, as
    `orjson.Fragment`s of their text: the API only writes them out again (app/core/fast_json.py), and parsing a job's
    config cost 8.8 µs of a job read. A caller that needs the values parses them itself."""
    for name in ("json", "jsonb"):
        await conn.set_type_codec(name, schema="pg_catalog", decoder=orjson.Fragment,
                                  encoder=lambda value: orjson.dumps(value).decode())


class _Connections:
    """Slots of asyncpg connections: each holds an open connection or None, a connection to make when next needed.
    A connection the server closed (a restart, a terminated backend) is made again when its slot is next taken. Taking
    an idle one never leaves the event loop's turn."""

    def __init__(self, url: URL, size: int):
        import asyncpg

        (self.dsn, self.connect_kwargs), self.size, self.closed = asyncpg_connect_args(url), size, False
        self._connect_fn, self._row = asyncpg.connect, _row_class()
        self._slots: asyncio.LifoQueue = asyncio.LifoQueue()

    async def open(self) -> None:
        opened = await asyncio.gather(*(self._connect() for _ in range(self.size)), return_exceptions=True)
        failed = [c for c in opened if isinstance(c, BaseException)]
        if failed:  # nothing half-open stays behind
            await asyncio.gather(*(c.close() for c in opened if not isinstance(c, BaseException)))
            raise failed[0]
        for conn in opened:
            self._slots.put_nowait(conn)

    async def _connect(self):
        conn = await self._connect_fn(self.dsn, record_class=self._row, **self.connect_kwargs)
        try:
            await _setup(conn)
        except BaseException:
            conn.terminate()
            raise
        return conn

    async def fetch(self, sql: str, args: list[Any]) -> list[Any]:
        """Raises TimeoutError when no connection comes free within POOL_WAIT_S."""
        if self.closed:
            raise RuntimeError("the hot reads' pool is closed")
        if self._slots.empty():
            async with asyncio.timeout(POOL_WAIT_S):
                conn = await self._slots.get()
        else:
            conn = self._slots.get_nowait()
        try:
            if conn is None or conn.is_closed():  # a connection the server closed while idle is made again
                conn = await self._connect()
            return await conn.fetch(sql, *args)
        finally:
            if self.closed and conn is not None:
                conn.terminate()
            else:
                self._slots.put_nowait(None if conn is None or conn.is_closed() else conn)

    async def close(self) -> None:
        """Close the idle connections; one still in use is closed when its read ends."""
        self.closed = True
        idle = [self._slots.get_nowait() for _ in range(self._slots.qsize())]
        await asyncio.gather(*(conn.close() for conn in idle if conn is not None))


class FastReads:
    """The API process's executor of hot reads: open() at startup, close() at shutdown."""

    def __init__(self, engine: Engine, size: int):
        self.engine = engine.execution_options(isolation_level="AUTOCOMMIT")  # SQLite: one statement, no BEGIN
        self.size = size
        self._compiled: dict[int, tuple[Executable, str, tuple[str, ...]]] = {}  # id -> (statement, SQL, names)
        self._pool = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lost: tuple[type[Exception], ...] = ()
        self._batches: dict[int, _Batch] = {}  # id(statement) -> the batch still taking keys

    @property
    def on_postgresql(self) -> bool:
        return self.engine.dialect.name == "postgresql"

    async def open(self) -> None:
        """Open the pool on this event loop. A pool serves only the loop that opened it: another lifespan of the same
        app (tests run several clients, each with a loop of its own, on one app) leaves it as it is, and reads from
        any other loop take the threadpool path."""
        if not self.on_postgresql or self._pool is not None:
            return
        import asyncpg
        from sqlalchemy.dialects.postgresql.asyncpg import PGDialect_asyncpg

        self._dialect = PGDialect_asyncpg(paramstyle="numeric_dollar")
        # What a server restart or a terminated backend raises on a pooled connection's next use; not a timeout
        # (TimeoutError is an OSError) nor a cancelled statement, which are not lost connections.
        self._lost = (asyncpg.ConnectionDoesNotExistError, asyncpg.PostgresConnectionError,
                      asyncpg.exceptions.AdminShutdownError, asyncpg.exceptions.CrashShutdownError,
                      asyncpg.InterfaceError, ConnectionError)
        self._loop = asyncio.get_running_loop()
        # Every connection opened now: a pool that grows on demand makes the read that finds all connections busy
        # wait for a new one's connect and set-up, tens of milliseconds on a loaded machine.
        pool = _Connections(self.engine.url, self.size)
        await pool.open()
        self._pool = pool

    async def close(self) -> None:
        if self._pool is not None and asyncio.get_running_loop() is self._loop:
            pool, self._pool = self._pool, None
            await pool.close()

    async def all(self, stmt: Executable, **params: Any) -> Sequence[Any]:
        """Every row of `stmt` with its bind parameters `params`."""
        if self._pool is None or asyncio.get_running_loop() is not self._loop:
            return await asyncio.to_thread(self._sync, stmt, params)
        sql, names = self._sql(stmt)
        args, pool = [params[name] for name in names], self._pool
        try:
            return await pool.fetch(sql, args)
        except self._lost as exc:  # the server closed connections (a restart): ask again, on one made anew
            log.warning("read retried after a lost database connection: %s", exc)
            return await pool.fetch(sql, args)

    async def one(self, stmt: Executable, **params: Any) -> Any | None:
        """The first row of `stmt`, or None."""
        rows = await self.all(stmt, **params)
        return rows[0] if rows else None

    async def keyed(self, stmt: Executable, column: str, key: Any) -> Any | None:
        """The row of `stmt` whose `column` is `key`, or None; `stmt` takes the bindparam `keys`, a list.

        Every keyed read of `stmt` that starts in one turn of the event loop joins one batch, sent as one statement
        on the loop's next turn: under load one round trip serves the requests that arrived together, and a quiet
        server waits one turn, microseconds. Sending the first read at once and batching only those that start
        while it is in flight cost a job read about 16 µs more of the API's CPU under load (bench/NOTES.md). A read
        joins only a batch not yet sent, so it still sees every write committed before it began."""
        loop, sid = asyncio.get_running_loop(), id(stmt)
        batch = self._batches.get(sid)
        if batch is None or batch.loop is not loop or len(batch.keys) >= BATCH_MAX:
            batch = self._batches[sid] = _Batch(loop)
        batch.keys.add(key)
        if batch.rows is None:  # after the key: an eager task factory would start the read at once
            batch.rows = loop.create_task(self._send(stmt, column, batch))
        return (await asyncio.shield(batch.rows)).get(key)

    async def _send(self, stmt: Executable, column: str, batch: _Batch) -> dict[Any, Any]:
        if self._batches.get(id(stmt)) is batch:
            del self._batches[id(stmt)]
        return {getattr(row, column): row for row in await self.all(stmt, keys=list(batch.keys))}

    def _sql(self, stmt: Executable) -> tuple[str, tuple[str, ...]]:
        found = self._compiled.get(id(stmt))
        if found is None:
            compiled = stmt.compile(dialect=self._dialect)
            # Only named bind parameters, all given per call: a literal or an IN list would need values compiled in.
            if compiled.params.keys() - {b.key for b in compiled.binds.values() if b.value is None} or \
                    "POSTCOMPILE" in str(compiled):
                raise ValueError(f"a fast read takes named bindparams only: {compiled}")
            found = self._compiled[id(stmt)] = (stmt, str(compiled), tuple(compiled.positiontup))
        return found[1], found[2]

    def _sync(self, stmt: Executable, params: dict[str, Any]) -> Sequence[Any]:
        with self.engine.connect() as conn:
            return conn.execute(stmt, params).all()
