"""`drop`: the engine's commands (train, evaluate) plus the service's: serve, api, worker, token, db upgrade."""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from contextlib import contextmanager
from typing import Iterator

from drop_engine.cli import build_parser as engine_parser

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


def cmd_db_upgrade(args: argparse.Namespace) -> int:
    from kernel.db import upgrade

    settings = _settings()
    settings.ensure_dirs()
    upgrade(settings.sqlalchemy_url)
    print("database is at the newest migration")
    return 0


def _with_sessions(run) -> int:
    """Run `run(sessionmaker)` against the configured database, once it is at the newest migration."""
    from kernel.db import make_engine, make_sessionmaker

    settings = _settings()
    if not _check_migrated(settings):
        return 2
    engine = make_engine(settings.sqlalchemy_url)
    try:
        return run(make_sessionmaker(engine))
    finally:
        engine.dispose()


def cmd_token_create(args: argparse.Namespace) -> int:
    from .core.auth import create_token

    def run(sessions) -> int:
        print(create_token(sessions, args.name))
        return 0

    return _with_sessions(run)


def cmd_token_list(args: argparse.Namespace) -> int:
    from .core.auth import list_tokens
    from .core.pages import iso

    def run(sessions) -> int:
        rows = list_tokens(sessions, args.owner)
        print(f"{'id':<30} {'owner':<20} {'created':<28} revoked")
        for token, owner in rows:
            print(f"{token.id:<30} {owner:<20} {iso(token.created_at):<28} {iso(token.revoked_at) or '-'}")
        return 0

    return _with_sessions(run)


def cmd_token_revoke(args: argparse.Namespace) -> int:
    from .core.auth import TokenNotFound, revoke_token
    from .core.pages import iso

    def run(sessions) -> int:
        try:
            token = revoke_token(sessions, args.token)
        except TokenNotFound as exc:
            print(f"drop: {exc}", file=sys.stderr)
            return 2
        print(f"token {token.id} revoked at {iso(token.revoked_at)}; the API refuses it within "
              f"DROP_TOKEN_CACHE_S ({_settings().token_cache_s:g} s)")
        return 0

    return _with_sessions(run)


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
    """Each process builds its app (and its logging) from the same DROP_ environment; the access log is ours."""
    return {"app": "app.main:served_app", "factory": True, "host": host, "port": port, "workers": workers,
            "log_config": None, "access_log": False, "timeout_graceful_shutdown": GRACEFUL_S}


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


def cmd_api(args: argparse.Namespace) -> int:
    settings = _settings()
    _configure_logs(settings)
    return _run_api(settings, args.host, args.port, args.workers or default_api_workers())


def cmd_worker(args: argparse.Namespace) -> int:
    serve_worker()  # before anything else: `drop serve` may die at any time
    settings = _settings()
    _configure_logs(settings, args.loglevel)
    settings.ensure_dirs()
    if not _check_migrated(settings):
        return 2
    from celery.bin.celery import celery

    concurrency = args.concurrency or settings.worker_concurrency
    celery.main(args=["-A", WORKER_APP, "worker", "--pool", "prefork", "-c", str(concurrency), "-Q", settings.queue,
                      "--without-gossip", "--without-mingle", "--without-heartbeat",
                      "-n", f"drop-{os.getpid()}@%h", "--loglevel", args.loglevel], standalone_mode=False)
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    """Embedded single-machine mode: migrate, then serve the API in this process and one worker in a child, stopped
    together by SIGTERM, SIGINT or SIGHUP (app/serving/embedded.py)."""
    if not args.auth:
        os.environ["DROP_AUTH_DISABLED"] = "true"
    os.environ.setdefault("DROP_LOG_FORMAT", "console")  # a person reads it; DROP_LOG_FORMAT=json for a collector
    code = cmd_db_upgrade(args)
    if code:
        return code
    settings = _settings()
    print(f"drop serve: data in {settings.data_dir.resolve()}, auth {'off' if settings.auth_disabled else 'on'}, "
          f"API on http://{args.host}:{args.port}", flush=True)
    import uvicorn

    from .serving.embedded import serve

    _configure_logs(settings)
    return serve(uvicorn.Config(**_uvicorn_options(args.host, args.port, 1)))


def build_parser() -> argparse.ArgumentParser:
    parser = engine_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))

    p = sub.add_parser("serve", help="API and one worker on this machine (SQLite, filesystem broker, no auth)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--auth", action="store_true", help="require bearer tokens even in embedded mode")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("api", help="the HTTP API alone (production: DROP_DATABASE_URL, DROP_BROKER_URL)")
    p.add_argument("--host", default="0.0.0.0")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help=f"API processes (default: one per core, at most 8; here {default_api_workers()})")
    p.set_defaults(func=cmd_api)

    p = sub.add_parser("worker", help="a Celery worker that runs training jobs")
    p.add_argument("--concurrency", type=int, default=None, help="jobs at once (default DROP_WORKER_CONCURRENCY)")
    p.add_argument("--loglevel", default="INFO")
    p.set_defaults(func=cmd_worker)

    p = sub.add_parser("token", help="API tokens")
    tsub = p.add_subparsers(dest="token_command", required=True)
    t = tsub.add_parser("create", help="create a token for an owner (created if new) and print it once")
    t.add_argument("--name", required=True)
    t.set_defaults(func=cmd_token_create)
    t = tsub.add_parser("list", help="list tokens (ids, owners, when created and revoked; never the secrets)")
    t.add_argument("--owner", help="only this owner's tokens")
    t.set_defaults(func=cmd_token_list)
    t = tsub.add_parser("revoke", help="revoke a token at once, by id, the start of an id, or the token itself")
    t.add_argument("token", metavar="ID_OR_TOKEN")
    t.set_defaults(func=cmd_token_revoke)

    p = sub.add_parser("db", help="database")
    dsub = p.add_subparsers(dest="db_command", required=True)
    d = dsub.add_parser("upgrade", help="apply migrations up to the newest")
    d.set_defaults(func=cmd_db_upgrade)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
