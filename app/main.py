"""The FastAPI application factory; refuses to start on a database that is not at the newest migration."""
from __future__ import annotations

import asyncio
import logging
from contextlib import asynccontextmanager, suppress
from typing import AsyncIterator

from fastapi import FastAPI

from kernel.db import make_engine, make_sessionmaker, schema_problem
from kernel.fast_reads import FastReads
from kernel.logs import configure, flush_access
from kernel.queue import enqueue, make_celery
from kernel.settings import Settings, get_settings

from .core import problems
from .core.body_limit import BodyLimit
from .core.body_timeout import IdleBody
from .core.openapi import operation_id
from .core.slots import stream_slots, upload_slots
from .core.token_cache import TokenCache
from .datasets import routes as datasets
from .datasets.validate import Validator
from .jobs import outputs
from .jobs import routes as jobs
from .jobs.event_bus import EventWaker, SharedReads, listen
from .jobs.metrics import JobMetrics
from .leftovers import sweep_abandoned
from .observability import health
from .observability.observe import ObserveRequests
from .serving.procs import supervised

log = logging.getLogger("drop.api")
JSON_BODY_LIMIT = 1 << 20


class NotMigrated(RuntimeError):
    pass


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()
    settings.ensure_dirs()
    engine = make_engine(settings.sqlalchemy_url)
    reason = schema_problem(engine)
    if reason:
        engine.dispose()
        raise NotMigrated(reason)
    # JSON bodies are small; only the dataset upload may be large, and it enforces its own limit while streaming.
    app = FastAPI(title="drop-rl", version="1", description="Offline RL training service (DROP, MOPO, MBPO)",
                  lifespan=_lifespan, generate_unique_id_function=operation_id)
    app.add_middleware(BodyLimit, limit=JSON_BODY_LIMIT, exempt={("POST", "/v1/datasets")})
    app.add_middleware(IdleBody, timeout=settings.body_idle_timeout_s)  # outside BodyLimit, which reads JSON bodies
    app.state.settings = settings
    app.state.engine = engine
    app.state.sessions = make_sessionmaker(engine)
    sweep_abandoned(settings, app.state.sessions)
    app.state.fast_reads = FastReads(engine, settings.db_pool_size)
    app.state.events = EventWaker()
    app.state.shared_reads = SharedReads()
    app.state.stream_slots = stream_slots(settings)
    app.state.upload_slots = upload_slots(settings)
    app.state.validator = Validator(settings)
    app.state.job_metrics = JobMetrics(engine)
    app.state.tokens = TokenCache(settings.token_cache_s)
    app.state.celery = make_celery(settings)
    app.state.enqueue = lambda job_id, runtime: enqueue(app.state.celery, settings, job_id, runtime)
    problems.install(app)
    build = app.build_middleware_stack  # outside Starlette's error middleware: 500s get an id, and their log lines too
    app.build_middleware_stack = lambda: ObserveRequests(build())
    for router in (health.router, datasets.router, jobs.router, outputs.router):
        app.include_router(router)
    return app


def served_app() -> FastAPI:
    """The app as `drop api` and `drop serve` run it, built in each uvicorn process: logging from the settings first."""
    supervised()
    settings = get_settings()
    configure(settings.log_format, settings.log_level)
    return create_app(settings)


@asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    """The hot reads' pool (kernel/fast_reads.py) and, on PostgreSQL, the listener for new job events
    (app/jobs/event_bus.py), while the app serves."""
    engine, fast_reads = app.state.engine, app.state.fast_reads
    await fast_reads.open()
    listener = None
    if engine.dialect.name == "postgresql":
        conninfo = engine.url.set(drivername="postgresql").render_as_string(hide_password=False)
        listener = asyncio.create_task(listen(conninfo, app.state.events))
    try:
        yield
    finally:
        try:
            if listener is not None:
                listener.cancel()
                with suppress(asyncio.CancelledError):
                    await listener
            await fast_reads.close()
            app.state.validator.close()
        finally:
            engine.dispose()  # the pool's connections now, not when the app is collected
            flush_access()
