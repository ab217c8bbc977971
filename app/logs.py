"""One logging setup for the API, the workers and `drop serve`: JSON lines for log collectors, or a readable console.

Every module keeps using the standard `logging` module; structlog only formats. Ids bound with `bound(...)` or
`structlog.contextvars.bind_contextvars` (request_id in the API, job_id, attempt and worker in a worker) are added to
every line logged in that context.
"""
from __future__ import annotations

import logging
from typing import Literal

import structlog

LogFormat = Literal["json", "console"]
bound = structlog.contextvars.bound_contextvars


def configure(fmt: LogFormat = "json", level: str = "INFO") -> None:
    """Route every logger (uvicorn's and Celery's included) through one handler on stderr in `fmt`."""
    shared = [
        structlog.contextvars.merge_contextvars,
        structlog.stdlib.add_logger_name,
        structlog.stdlib.add_log_level,
        structlog.stdlib.ExtraAdder(),
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    if fmt == "json":
        render = [structlog.processors.format_exc_info, structlog.processors.JSONRenderer()]
    else:
        render = [structlog.dev.ConsoleRenderer(colors=False)]
    handler = logging.StreamHandler()
    handler.setFormatter(structlog.stdlib.ProcessorFormatter(
        foreign_pre_chain=shared, processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, *render]))
    root = logging.getLogger()
    root.handlers = [handler]
    root.setLevel(level.upper())
    for name in ("uvicorn", "uvicorn.error", "celery"):
        logger = logging.getLogger(name)
        logger.handlers, logger.propagate = [], True
    access = logging.getLogger("uvicorn.access")  # the API writes its own access line, with the request id
    access.handlers, access.propagate = [], False
