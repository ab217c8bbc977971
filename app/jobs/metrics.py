"""Job metrics computed from the database at scrape time: jobs by status, queue wait, attempts, run seconds and
dynamics-cache hits and misses.

The job rows are the truth whichever worker (on whichever machine, in whichever short-lived pool process) ran a job,
so aggregating them in SQL needs no metrics server in the workers and loses nothing when a worker dies. Each scrape
reads the jobs table, and the deleted jobs' counts (`DeletedJob`), once or twice: cheap at this service's scale.
"""
from __future__ import annotations

from typing import Iterable, Sequence

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from sqlalchemy import case, func, select, union_all
from sqlalchemy.engine import Engine

from kernel.job_state import FINAL, JobStatus, status_in
from kernel.models import DeletedJob, Job

QUEUE_WAIT_BUCKETS = (1, 5, 15, 60, 300, 900, 3600, 4 * 3600, 24 * 3600)
RUN_BUCKETS = (10, 60, 300, 900, 3600, 3 * 3600, 12 * 3600, 24 * 3600, 72 * 3600)


def _histogram_columns(column, buckets: Sequence[float]) -> list:
    """Cumulative bucket counts, count and sum of a nullable column, as one row of aggregates."""
    return [*(func.count(case((column <= b, 1))) for b in buckets), func.count(column),
            func.coalesce(func.sum(column), 0.0)]


def _histogram(name: str, doc: str, buckets: Sequence[float], values: Sequence) -> HistogramMetricFamily:
    *counts, total, summed = values
    pairs = [(str(float(b)), int(n)) for b, n in zip(buckets, counts)] + [("+Inf", int(total))]
    return HistogramMetricFamily(name, doc, buckets=pairs, sum_value=float(summed))


class JobMetrics:
    """A prometheus_client collector over the jobs table."""

    def __init__(self, engine: Engine):
        self.engine = engine

    def collect(self) -> Iterable[Metric]:
        # Deleted jobs still count (DeletedJob): a counter read from rows would otherwise go down when one goes.
        # Each was final when deleted, so its run seconds count as a finished job's.
        counted = union_all(
            select(Job.attempts, Job.dynamics_from_cache, Job.queue_wait_s,
                   case((status_in(FINAL), Job.run_s)).label("run_s")),
            select(DeletedJob.attempts, DeletedJob.dynamics_from_cache, DeletedJob.queue_wait_s, DeletedJob.run_s),
        ).subquery()
        aggregates = select(
            func.coalesce(func.sum(counted.c.attempts), 0),
            func.count(case((counted.c.dynamics_from_cache.is_(True), 1))),
            func.count(case((counted.c.dynamics_from_cache.is_(False), 1))),
            *_histogram_columns(counted.c.queue_wait_s, QUEUE_WAIT_BUCKETS),
            *_histogram_columns(counted.c.run_s, RUN_BUCKETS),
        )
        with self.engine.connect() as conn:
            by_status = dict(conn.execute(select(Job.status, func.count()).group_by(Job.status)).all())
            attempts, hits, misses, *rest = conn.execute(aggregates).one()
        jobs = GaugeMetricFamily("drop_jobs", "Jobs by status", labels=["status"])
        for status in JobStatus:
            jobs.add_metric([status.value], by_status.get(status.value, 0))
        yield jobs
        # A gauge, not a counter: an attempt handed back by a stopping worker is taken off again, and a counter that
        # goes down reads as a reset.
        yield GaugeMetricFamily("drop_job_attempts", "Attempts started over all jobs (an attempt handed back by a "
                                "stopping worker does not count)", value=int(attempts))
        cache = CounterMetricFamily("drop_dynamics_cache_lookups", "Jobs whose dynamics ensemble came from the model "
                                    "cache (hit) or was trained (miss)", labels=["result"])
        cache.add_metric(["hit"], hits)
        cache.add_metric(["miss"], misses)
        yield cache
        split = len(QUEUE_WAIT_BUCKETS) + 2
        yield _histogram("drop_job_queue_wait_seconds", "Seconds from a job's creation to its first claim by a worker",
                         QUEUE_WAIT_BUCKETS, rest[:split])
        yield _histogram("drop_job_run_seconds", "Seconds a job's attempts ran, summed, once it finished",
                         RUN_BUCKETS, rest[split:])
