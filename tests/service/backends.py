"""The real PostgreSQL and Redis the service tests run on, and throwaway databases on that PostgreSQL."""
from __future__ import annotations

import secrets
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Iterator

import psycopg

PG_ADMIN = "postgresql://postgres@127.0.0.1:5432/postgres"
REDIS_URL = "redis://127.0.0.1:6379/0"


@contextmanager
def database() -> Iterator[str]:
    """A new empty PostgreSQL database, dropped afterwards."""
    name = f"drop_test_{secrets.token_hex(4)}"
    with psycopg.connect(PG_ADMIN, autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    try:
        yield f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}"
    finally:
        with psycopg.connect(PG_ADMIN, autocommit=True) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


@contextmanager
def migrated_engine(kind: str, folder: Path, owner: str):
    """An engine on a new migrated database, `kind` "sqlite" (a file in `folder`) or "postgresql", holding the owner
    `owner`, and nothing else: no worker's reaper sends its jobs. Disposed of afterwards."""
    from kernel.db import make_engine, make_sessionmaker, upgrade
    from kernel.models import Owner

    with database() if kind == "postgresql" else nullcontext(f"sqlite:///{folder / 'jobs.db'}") as url:
        upgrade(url)
        engine = make_engine(url)
        with make_sessionmaker(engine).begin() as s:
            s.add(Owner(id=owner, name=owner))
        try:
            yield engine
        finally:
            engine.dispose()
