"""A database server that takes the TCP connection and never answers fails a connect in bounded time, for every
connection made from the engine's URL: the drivers' own defaults would hold the request or worker that asked for 130 s
(psycopg) or 60 s (asyncpg)."""
from __future__ import annotations

import asyncio
import socket
import time

import asyncpg
import psycopg
import pytest
from sqlalchemy.exc import OperationalError

from kernel import db, fast_reads
from kernel.db import make_engine


@pytest.fixture
def silent_server():
    """A listening socket nobody accepts on: the kernel completes the handshake, then nothing is ever said."""
    with socket.create_server(("127.0.0.1", 0), backlog=8) as sock:
        yield f"postgresql+psycopg://drop@127.0.0.1:{sock.getsockname()[1]}/drop"


def _gives_up(connect) -> None:
    started = time.monotonic()
    with pytest.raises((OperationalError, psycopg.OperationalError, TimeoutError)):
        connect()
    assert time.monotonic() - started < 10


def test_every_connection_from_the_engine_gives_up(silent_server, monkeypatch):
    """The ORM's pool, the hot reads' asyncpg connections and the event listener's psycopg connection."""
    monkeypatch.setattr(db, "CONNECT_TIMEOUT_S", 2)
    monkeypatch.delenv("PGCONNECT_TIMEOUT", raising=False)
    engine = make_engine(silent_server)
    assert engine.url.query["connect_timeout"] == "2"
    _gives_up(engine.connect)
    engine.dispose()
    dsn, kwargs = fast_reads.asyncpg_connect_args(engine.url)
    _gives_up(lambda: asyncio.run(asyncpg.connect(dsn, **kwargs)))
    conninfo = engine.url.set(drivername="postgresql").render_as_string(hide_password=False)  # as app.main's listener
    _gives_up(lambda: asyncio.run(psycopg.AsyncConnection.connect(conninfo)))


def test_a_timeout_of_the_url_or_environment_is_kept(silent_server, monkeypatch):
    monkeypatch.setattr(db, "CONNECT_TIMEOUT_S", 600)
    monkeypatch.delenv("PGCONNECT_TIMEOUT", raising=False)
    own = make_engine(f"{silent_server}?connect_timeout=2")
    assert own.url.query["connect_timeout"] == "2"
    _gives_up(own.connect)
    monkeypatch.setenv("PGCONNECT_TIMEOUT", "3")
    assert make_engine(silent_server).url.query["connect_timeout"] == "3"
