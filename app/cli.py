"""The service's commands: serve, api, worker, token, db upgrade. The `drop` command (drop_cli) adds them to the
engine's; `python -m app.cli` runs them alone, as `drop serve` does for its worker."""
from __future__ import annotations

import os
import shutil
import sys
import tempfile
from contextlib import contextmanager
from typing import Iterator

import click

from drop_engine.cli import Group, run

from .serving.procs import SUPERVISOR_ENV, serve_worker

MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"  # app.observability.metrics reads it: set here before it is imported
GRACEFUL_S = 5  # open event streams never end by themselves: a stopping API closes them after this
WORKER_APP = "worker.tasks:celery"  # named, as uvicorn's app is: the API's package does not import the worker's


def _settings():
    from kernel.settings import get_settings

    get_settings.cache_clear()
    return get_settings()


def _check_migrated(settings) -> bool:
    from kernel.db import make_engine, schema_problem

    engine = make_engine(settings.sqlalchemy_url)
    try:
        reason = schema_problem(engine)
    finally:
        engine.dispose()
    if reason:
        print(f"drop: {reason}", file=sys.stderr)
        return False
    return True


@click.group(cls=Group)
def service() -> None:
    """The drop-rl service."""


@service.group()
def db() -> None:
    """Database."""


@db.command("upgrade")
def db_upgrade() -> int:
    """Apply migrations up to the newest."""
    return _upgrade_db()


def _upgrade_db() -> int:
    from kernel.db import upgrade

    settings = _settings()
    settings.ensure_dirs()
    upgrade(settings.sqlalchemy_url)
    print("database is at the newest migration")
    return 0


def _with_sessions(use) -> int:
    """Run `use(sessionmaker)` against the configured database, once it is at the newest migration."""
    from kernel.db import make_engine, make_sessionmaker

    settings = _settings()
    if not _check_migrated(settings):
        return 2
    engine = make_engine(settings.sqlalchemy_url)
    try:
        return use(make_sessionmaker(engine))
    finally:
        engine.dispose()


@service.group()
def token() -> None:
    """API tokens."""


@token.command("create")
@click.option("--name", required=True, help="the owner (created if new)")
def token_create(name: str) -> int:
    """Create a token for an owner and print it once."""
    from .core.auth import create_token

    def create(sessions) -> int:
        print(create_token(sessions, name))
        return 0

    return _with_sessions(create)


@token.command("list")
@click.option("--owner", help="only this owner's tokens")
def token_list(owner: str | None) -> int:
    """List tokens: ids, owners, when created and revoked; never the secrets."""
    from .core.auth import list_tokens
    from .core.pages import iso

    def show(sessions) -> int:
        rows = list_tokens(sessions, owner)
        print(f"{'id':<30} {'owner':<20} {'created':<28} revoked")
        for row, row_owner in rows:
            print(f"{row.id:<30} {row_owner:<20} {iso(row.created_at):<28} {iso(row.revoked_at) or '-'}")
        return 0

    return _with_sessions(show)


@token.command("revoke")
@click.argument("id_or_token", metavar="ID_OR_TOKEN")
def token_revoke(id_or_token: str) -> int:
    """Revoke a token at once, by id, the start of an id, or the token itself."""
    from .core.auth import TokenNotFound, revoke_token
    from .core.pages import iso

    def revoke(sessions) -> int:
        try:
            revoked = revoke_token(sessions, id_or_token)
        except TokenNotFound as exc:
            print(f"drop: {exc}", file=sys.stderr)
            return 2
        print(f"token {revoked.id} revoked at {iso(revoked.revoked_at)}; the API refuses it within "
              f"DROP_TOKEN_CACHE_S ({_settings().token_cache_s:g} s)")
        return 0

    return _with_sessions(revoke)


def default_api_workers() -> int:
    """One API process per core this process may use, up to 4: the API is async, so more would only contend, and
    each process holds a database pool of its own (README: the connection budget)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, 4))


@contextmanager
def _metrics_dir(workers: int) -> Iterator[None]:
    """Several API processes share their metrics through files in PROMETHEUS_MULTIPROC_DIR (see
    app/observability/metrics.py): a fresh folder for this run unless the operator named one. Set before any process
    imports prometheus_client."""
    if workers == 1 or os.environ.get(MULTIPROC_ENV):
        yield
        return
    folder = tempfile.mkdtemp(prefix="drop-metrics-")
    os.environ[MULTIPROC_ENV] = folder
    try:
        yield
    finally:
        os.environ.pop(MULTIPROC_ENV, None)
        shutil.rmtree(folder, ignore_errors=True)


@contextmanager
def _supervising(workers: int) -> Iterator[None]:
    """Worker processes learn their supervisor's pid, to die with it (app/serving/procs.py)."""
    if workers == 1:
        yield
        return
    os.environ[SUPERVISOR_ENV] = str(os.getpid())
    try:
        yield
    finally:
        os.environ.pop(SUPERVISOR_ENV, None)


def _uvicorn_options(host: str, port: int, workers: int) -> dict:
    """Each process builds its app (and its logging) from the same DROP_ environment; the access log is ours.

    asyncio's loop even where uvloop is installed (uvicorn's `auto` would take it): uvloop saved health checks and
    job reads the same few µs, and it closes connections beyond the descriptor limit without the accept-error line
    that tells an operator why (bench/NOTES.md)."""
    from .serving.http_protocol import IMPORT_PATH

    return {"app": "app.main:served_app", "factory": True, "host": host, "port": port, "workers": workers,
            "log_config": None, "access_log": False, "timeout_graceful_shutdown": GRACEFUL_S, "http": IMPORT_PATH,
            "loop": "asyncio"}


def _run_api(settings, host: str, port: int, workers: int) -> int:
    import uvicorn

    if not _check_migrated(settings):
        return 2
    with _metrics_dir(workers), _supervising(workers):
        uvicorn.run(**_uvicorn_options(host, port, workers))
    return 0


def _configure_logs(settings, level: str | None = None) -> None:
    from kernel.logs import configure

    configure(settings.log_format, level or settings.log_level)


@service.command()
@click.option("--host", default="0.0.0.0", show_default=True)
@click.option("--port", type=int, default=8000, show_default=True)
@click.option("--workers", type=int, default=None, metavar="N",
              help=f"API processes (default: one per core, at most 4; here {default_api_workers()})")
def api(host: str, port: int, workers: int | None) -> int:
    """The HTTP API alone. In production, with DROP_DATABASE_URL and DROP_BROKER_URL."""
    settings = _settings()
    _configure_logs(settings)
    return _run_api(settings, host, port, workers or default_api_workers())


@service.command()
@click.option("--concurrency", type=int, default=None, help="jobs at once (default DROP_WORKER_CONCURRENCY)")
@click.option("--loglevel", default="INFO", show_default=True)
def worker(concurrency: int | None, loglevel: str) -> int:
    """A Celery worker that runs training jobs."""
    serve_worker()  # before anything else: `drop serve` may die at any time
    settings = _settings()
    _configure_logs(settings, loglevel)
    settings.ensure_dirs()
    if not _check_migrated(settings):
        return 2
    from celery.bin.celery import celery

    celery.main(args=["-A", WORKER_APP, "worker", "--pool", "prefork", "-c",
                      str(concurrency or settings.worker_concurrency), "-Q", settings.queue, "--without-gossip",
                      "--without-mingle", "--without-heartbeat", "-n", f"drop-{os.getpid()}@%h",
                      "--loglevel", loglevel], standalone_mode=False)
    return 0


@service.command()
@click.option("--host", default="127.0.0.1", show_default=True)
@click.option("--port", type=int, default=8000, show_default=True)
@click.option("--auth", is_flag=True, help="require bearer tokens even in embedded mode")
def serve(host: str, port: int, auth: bool) -> int:
    """The API and one worker on this machine. SQLite, a filesystem broker and no auth: it migrates, then serves the
    API in this process and the worker in a child, stopped together by SIGTERM, SIGINT or SIGHUP
    (app/serving/embedded.py)."""
    if not auth:
        os.environ["DROP_AUTH_DISABLED"] = "true"
    os.environ.setdefault("DROP_LOG_FORMAT", "console")  # a person reads it; DROP_LOG_FORMAT=json for a collector
    code = _upgrade_db()
    if code:
        return code
    settings = _settings()
    print(f"drop serve: data in {settings.data_dir.resolve()}, auth {'off' if settings.auth_disabled else 'on'}, "
          f"API on http://{host}:{port}", flush=True)
    import uvicorn

    from .serving.embedded import serve as run_embedded

    _configure_logs(settings)
    return run_embedded(uvicorn.Config(**_uvicorn_options(host, port, 1)))


def main(argv: list[str] | None = None) -> int:
    return run(service, argv)


if __name__ == "__main__":
    sys.exit(main())
