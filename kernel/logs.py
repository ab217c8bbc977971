"""One logging setup for the API, the workers and `drop serve`: JSON lines for log collectors, or a readable console.

Every module keeps using the standard `logging` module; structlog only formats. Ids bound with `bound(...)` or
`structlog.contextvars.bind_contextvars` (request_id in the API, job_id, attempt and worker in a worker) are added to
every line logged in that context.
"""
from __future__ import annotations

import asyncio
import json
import logging
import select
import sys
import threading
import time
from datetime import datetime, timezone
from typing import Callable, Literal

import structlog

LogFormat = Literal["json", "console"]
bound = structlog.contextvars.bound_contextvars
# asyncio's line, with a traceback, for each connection it cannot accept; out of file descriptors, thousands a second.
ACCEPT_ERROR = "socket.accept() out of system resource"
ACCEPT_ERROR_EVERY_S = 10.0


class OncePer(logging.Filter):
    """Let through one record whose message starts with `prefix` per `every_s`; the next one let through says how
    many were dropped in between."""

    def __init__(self, prefix: str, every_s: float, clock: Callable[[], float] = time.monotonic):
        super().__init__()
        self.prefix, self.every_s, self.clock = prefix, every_s, clock
        self._next, self._dropped = float("-inf"), 0
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        if not record.getMessage().startswith(self.prefix):
            return True
        now = self.clock()
        with self._lock:
            if now < self._next:
                self._dropped += 1
                return False
            self._next, dropped, self._dropped = now + self.every_s, self._dropped, 0
        if dropped:
            record.msg, record.args = f"{record.getMessage()}\n({dropped} more dropped since the last)", ()
        return True


class StderrHandler(logging.StreamHandler):
    """Writes to `sys.stderr` as it is when a line is written, as logging's own last-resort handler does, unless
    `setStream` fixed a stream. A handler holding the stderr of its creation writes to a closed file once that
    stderr is swapped and closed (pytest's per-test capture), and every line then prints a traceback instead."""

    def __init__(self) -> None:
        super().__init__()
        self._fixed = None

    @property
    def stream(self):
        return sys.stderr if self._fixed is None else self._fixed

    @stream.setter
    def stream(self, value) -> None:
        self._fixed = value


ACCESS_LOGGER = "drop.access"
ACCESS_FLUSH_S, ACCESS_BATCH = 0.2, 256
ACCESS_FIELDS = frozenset(("event", "logger", "level", "method", "path", "status", "ms", "timestamp"))
_access_logger = logging.getLogger(ACCESS_LOGGER)


def _access_through_logging(method: str, path: str, status: int, ms: float) -> None:
    _access_logger.info("request", extra={"method": method, "path": path, "status": status, "ms": ms})


class AccessWriter:
    """The access line in JSON, rendered here and written to `handler`'s stream: the same fields a record of
    "drop.access" gets, at a fraction of the cost. Through `logging` and structlog's formatter (a LogRecord made,
    copied and walked for extras) a line took about 22 µs, and its write a syscall: together a fifth of a /healthz
    answer, once per request. Lines wait up to ACCESS_FLUSH_S and go out together; `flush()` at shutdown, so only a
    killed process loses them."""

    def __init__(self, handler: logging.StreamHandler):
        self.handler, self._pending, self._timer = handler, [], None
        self._encode = json.JSONEncoder(ensure_ascii=True, default=repr).encode
        self._second = -1, ""

    def _timestamp(self) -> str:
        """ISO 8601 in UTC to the microsecond, the date and time formatted once a second (3.7 µs against 0.5)."""
        now = time.time()
        second, stamp = self._second
        if int(now) != second:
            second = int(now)
            stamp = datetime.fromtimestamp(second, timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")
            self._second = second, stamp  # one assignment: another thread sees the old pair or the new
        return f"{stamp}.{int((now - second) * 1e6):06d}Z"

    def __call__(self, method: str, path: str, status: int, ms: float) -> None:
        # The JSON a dict of these fields would encode to, written out: only the strings go through the encoder. A
        # bound variable named as one of the line's own fields gives way to it, as structlog's merge does.
        text = json.encoder.encode_basestring_ascii
        bound_now = structlog.contextvars.get_contextvars()
        context = "".join(f"{text(k)}: {self._encode(v)}, " for k, v in bound_now.items() if k not in ACCESS_FIELDS)
        line = (f'{{"event": "request", {context}"logger": "{ACCESS_LOGGER}", "level": "info", '
                f'"method": {text(method)}, "path": {text(path)}, "status": {int(status)}, "ms": {float(ms)!r}, '
                f'"timestamp": "{self._timestamp()}"}}\n')
        with self.handler.lock:
            self._pending.append(line)
            full = len(self._pending) >= ACCESS_BATCH
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no event loop here to flush later: now
            loop = None
        if full or loop is None:
            self.flush()
        elif self._timer is None or loop.time() > self._timer.when() + ACCESS_FLUSH_S:  # or one whose loop is gone
            self._timer = loop.call_later(ACCESS_FLUSH_S, self.flush)

    def flush(self) -> None:
        """Write what waits, in writes of at most PIPE_BUF bytes of whole lines: a pipe shared by several API
        processes keeps each such write whole, so their lines never splice."""
        with self.handler.lock:
            pending, self._pending, self._timer = self._pending, [], None
            chunk: list[str] = []
            size = 0
            try:
                for line in pending:
                    if chunk and size + len(line) > select.PIPE_BUF:
                        self.handler.stream.write("".join(chunk))
                        chunk, size = [], 0
                    chunk.append(line)
                    size += len(line)
                if chunk:
                    self.handler.stream.write("".join(chunk))
                self.handler.stream.flush()
            except Exception:  # as StreamHandler.emit: report it, never fail the request that logged
                self.handler.handleError(logging.makeLogRecord({"msg": "access lines", "name": ACCESS_LOGGER}))


# The API's line per request (app/observability/observe.py); configure() makes it an AccessWriter for JSON logs.
access_line: Callable[[str, str, int, float], None] = _access_through_logging


def flush_access() -> None:
    """Write the access lines still waiting (the API's shutdown)."""
    if isinstance(access_line, AccessWriter):
        access_line.flush()


def configure(fmt: LogFormat = "json", level: str = "INFO") -> None:
    """Route every logger (uvicorn's and Celery's included) through one handler on stderr in `fmt`."""
    global access_line
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
    handler = StderrHandler()
    handler.addFilter(OncePer(ACCEPT_ERROR, ACCEPT_ERROR_EVERY_S))
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
    if fmt != "json" or not _access_logger.isEnabledFor(logging.INFO):
        access_line = _access_through_logging
    else:
        access_line = AccessWriter(handler)
