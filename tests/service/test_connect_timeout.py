"""A database server that takes the TCP connection and never answers fails a connect in bounded time: libpq and
asyncpg would otherwise wait for ever and 60 s, holding the request or the worker that asked."""
from __future__ import annotations

import asyncio
import socket
import time

import asyncpg
import pytest
from sqlalchemy.engine import make_url
from sqlalchemy.exc import OperationalError

from kernel import db, fast_reads
from kernel.db import make_engine


@pytest.fixture
def silent_server():
    """A listening socket nobody accepts on: the kernel completes the handshake, then nothing is ever said."""
    with socket.create_server(("127.0.0.1", 0), backlog=8) as sock:
        yield f"postgresql+psycopg://drop@127.0.0.1:{sock.getsockname()[1]}/drop"


def test_orm_connect_gives_up(silent_server, monkeypatch):
    monkeypatch.setattr(db, "CONNECT_TIMEOUT_S", 2)
    engine = make_engine(silent_server)
    started = time.monotonic()
    with pytest.raises(OperationalError, match="timeout"):
        engine.connect()
    assert time.monotonic() - started < 10
    engine.dispose()


def test_url_keeps_its_own_timeout(silent_server, monkeypatch):
    """A URL that names connect_timeout is not overridden by the default."""
    monkeypatch.setattr(db, "CONNECT_TIMEOUT_S", 600)
    engine = make_engine(f"{silent_server}?connect_timeout=2")
    started = time.monotonic()
    with pytest.raises(OperationalError, match="timeout"):
        engine.connect()
    assert time.monotonic() - started < 10
    engine.dispose()


def test_hot_reads_connect_gives_up(silent_server, monkeypatch):
    monkeypatch.setattr(fast_reads, "CONNECT_TIMEOUT_S", 1)
    dsn, kwargs = fast_reads.asyncpg_connect_args(make_url(silent_server))
    started = time.monotonic()
    with pytest.raises(TimeoutError):
        asyncio.run(asyncpg.connect(dsn, **kwargs))
    assert time.monotonic() - started < 10
