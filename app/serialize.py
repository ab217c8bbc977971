"""Rows to API objects: every object carries id, object and created_at."""
from __future__ import annotations

from datetime import datetime, timezone

from kernel.models import Dataset, Job, JobCheckpoint, JobEvaluation, JobEvent, JobMetric


def iso(value: datetime | None) -> str | None:
    if value is None:
        return None
    if value.tzinfo is None:
        value = value.replace(tzinfo=timezone.utc)
    return value.astimezone(timezone.utc).isoformat().replace("+00:00", "Z")


def dataset(row: Dataset) -> dict:
    return {
        "id": row.id, "object": "dataset", "created_at": iso(row.created_at), "name": row.name,
        "format": row.format, "size_bytes": row.size_bytes, "decoded_bytes": row.decoded_bytes, "sha256": row.sha256, "env": row.env,
        "obs_dim": row.obs_dim, "act_dim": row.act_dim, "report": row.report,
    }


def job(row: Job) -> dict:
    return {
        "id": row.id, "object": "job", "created_at": iso(row.created_at), "status": row.status,
        "dataset_id": row.dataset_id, "algorithm": row.algorithm, "env": row.env, "preset": row.preset,
        "overrides": row.overrides, "seed": row.seed, "progress": row.progress, "latest_metrics": row.latest_metrics,
        "best_score": row.best_score, "last_score": row.last_score, "best_epoch": row.best_epoch,
        "final_score": row.final_score,
        "error": {"code": row.error_code, "message": row.error_message} if row.error_code else None,
        "attempts": row.attempts, "max_attempts": row.max_attempts, "max_runtime_s": row.max_runtime_s,
        "started_at": iso(row.started_at), "finished_at": iso(row.finished_at), "heartbeat_at": iso(row.heartbeat_at),
        "config": row.config,
    }


def event(row: JobEvent) -> dict:
    return {"id": row.id, "object": "job.event", "created_at": iso(row.created_at), "type": row.type,
            "message": row.message, "data": row.data}


def metric(row: JobMetric) -> dict:
    return {"id": row.id, "object": "job.metric", "created_at": iso(row.created_at), "name": row.name,
            "step": row.step, "value": row.value}


def evaluation(row: JobEvaluation) -> dict:
    return {"id": row.id, "object": "job.evaluation", "created_at": iso(row.created_at), "epoch": row.epoch,
            "mean_return": row.mean_return, "normalized_score": row.normalized_score}


def checkpoint(row: JobCheckpoint) -> dict:
    return {"id": row.id, "object": "job.checkpoint", "created_at": iso(row.created_at), "epoch": row.epoch,
            "step": row.step, "size_bytes": row.size_bytes}


def fetch_page(s, query, to_dict, limit: int) -> dict:
    """Run an ordered query for one row past the page, which tells whether there is more."""
    rows = list(s.scalars(query.limit(limit + 1)))
    return page([to_dict(r) for r in rows[:limit]], len(rows) > limit)


def page(items: list[dict], has_more: bool) -> dict:
    return {"object": "list", "data": items, "has_more": has_more,
            "next_after": items[-1]["id"] if items and has_more else None}
