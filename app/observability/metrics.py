"""Prometheus metrics of the API processes (HTTP requests, uploads) and the text the `/metrics` endpoint serves.

With several API processes (`drop api --workers N`) each writes its samples to files in PROMETHEUS_MULTIPROC_DIR,
which `drop api` sets, and a scrape of any one process sums them all. Job metrics are not kept here: they are
computed from the database at scrape time (app/jobs/metrics.py), so every worker's jobs count without workers serving
metrics of their own.
"""
from __future__ import annotations

import functools
import os
from typing import Awaitable, Callable, ParamSpec, TypeVar

from prometheus_client import REGISTRY, CollectorRegistry, Counter, Histogram, disable_created_metrics, generate_latest
from prometheus_client.multiprocess import MultiProcessCollector
from prometheus_client.registry import Collector

from ..core.problems import Problem

MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"
P = ParamSpec("P")
T = TypeVar("T")
disable_created_metrics()  # a `_created` series per counter doubles the output and no dashboard reads it
LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)

HTTP_REQUESTS = Counter("drop_http_requests", "HTTP requests answered, by method, route template and status",
                        ["method", "route", "status"])
HTTP_LATENCY = Histogram("drop_http_request_duration_seconds",
                         "Seconds from a request's arrival to its response's first byte (a stream's start, not its "
                         "end), by method, route template and status", ["method", "route", "status"],
                         buckets=LATENCY_BUCKETS)
UPLOAD_BYTES = Counter("drop_upload_bytes", "Bytes of dataset uploads received in full")
VALIDATION_SECONDS = Histogram("drop_upload_validation_duration_seconds",
                               "Seconds the validator subprocess took per upload",
                               buckets=(0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0))
UPLOAD_REJECTIONS = Counter("drop_upload_rejections", "Dataset uploads refused, by problem code", ["code"])


def counting_rejections(endpoint: Callable[P, Awaitable[T]]) -> Callable[P, Awaitable[T]]:
    """Wrap the upload endpoint: count a refused upload by the problem code it answers with."""
    @functools.wraps(endpoint)
    async def wrapper(*args: P.args, **kwargs: P.kwargs) -> T:
        try:
            return await endpoint(*args, **kwargs)
        except Problem as exc:
            UPLOAD_REJECTIONS.labels(exc.code).inc()
            raise

    return wrapper


def exposition(jobs: Collector) -> bytes:
    """The text format of this process's metrics (or all processes' in multiprocess mode) plus the job metrics."""
    if os.environ.get(MULTIPROC_ENV):
        registry = CollectorRegistry()
        MultiProcessCollector(registry)
    else:
        registry = REGISTRY
    own = CollectorRegistry()
    own.register(jobs)
    return generate_latest(registry) + generate_latest(own)
