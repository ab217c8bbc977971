"""Alembic environment: the URL comes from the Config (set by `drop db upgrade`) or else from DROP_ settings."""
from alembic import context

from kernel.db import make_engine
from kernel.models import Base
from kernel.settings import Settings

config = context.config
url = config.get_main_option("sqlalchemy.url") or Settings().sqlalchemy_url


def run_offline() -> None:
    context.configure(url=url, target_metadata=Base.metadata, literal_binds=True, render_as_batch=True)
    with context.begin_transaction():
        context.run_migrations()


def run_online() -> None:
    engine = make_engine(url)
    with engine.connect() as conn:
        sqlite = conn.dialect.name == "sqlite"
        if sqlite:  # batch mode recreates a table: its DROP must not cascade to the rows that refer to it
            _foreign_keys(conn, "OFF")
        context.configure(connection=conn, target_metadata=Base.metadata, render_as_batch=True)
        with context.begin_transaction():
            context.run_migrations()
        if sqlite:
            _foreign_keys(conn, "ON")
    engine.dispose()


def _foreign_keys(conn, state: str) -> None:
    """SQLite's foreign key enforcement, switched outside any transaction (inside one the PRAGMA does nothing)."""
    conn.exec_driver_sql(f"PRAGMA foreign_keys={state}")
    conn.commit()


if context.is_offline_mode():
    run_offline()
else:
    run_online()
