"""The real PostgreSQL and Redis the service tests run on, and throwaway databases on that PostgreSQL."""
from __future__ import annotations

import secrets
from contextlib import contextmanager
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
