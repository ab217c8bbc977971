"""The job objects the API answers with: their response models, so the OpenAPI schema tells clients (and the schema
fuzz test) exactly what comes back, and the dicts rows become. Where a route has FastAPI check its answer, it checks
these dicts against these models on the way out."""
from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from drop_engine.scores import FINAL_WINDOW, Which
from kernel.job_state import JobStatus
from kernel.models import Job, JobCheckpoint, JobEvaluation, JobEvent, JobMetric

from ..core.choices import Algorithm, EnvName, Preset
from ..core.pages import iso, timestamp


class JobError(BaseModel):
    code: str
    message: str | None


class JobDynamics(BaseModel):
    """The dynamics ensemble the job trains on: the model cache's key for it (the sha256 of the dataset's content, the
    dynamics config and the seed), whether it came from the cache, and its fit."""
    cache_key: str | None = Field(None, description="null where the run's checkpoint predates the model cache")
    from_cache: bool | None = Field(None, description="loaded from the model cache instead of trained for this job")
    epochs: int = Field(description="epochs it was trained for")
    holdout_mse: list[float] = Field(description="each member's error on the held-out rows")
    elites: list[int] = Field(description="the members the rollouts use")
    seconds: float = Field(description="what the fit took (in the job that trained it, if from the cache)")
    stopped_by: str = Field(description="patience, max_epochs or max_seconds")


class JobOut(BaseModel):
    id: str
    object: Literal["job"]
    created_at: str = timestamp()
    status: JobStatus
    dataset_id: str | None = Field(description="null once the dataset is deleted")
    algorithm: Algorithm
    env: EnvName
    preset: Preset
    overrides: dict[str, Any]
    seed: int
    progress: dict[str, Any] | None
    latest_metrics: dict[str, Any] | None
    best_score: float | None = Field(description="the highest normalised score of any evaluation so far")
    last_score: float | None = Field(description="the normalised score of the latest evaluation")
    best_epoch: int | None = Field(description="the epoch of best_score (the earlier of ties): the `which=best` "
                                               "policy's")
    final_score: float | None = Field(description=f"the mean normalised score of the last {FINAL_WINDOW} evaluations "
                                                  "(fewer if fewer ran): steadier than last_score")
    error: JobError | None
    attempts: int
    max_attempts: int
    max_runtime_s: int
    started_at: str | None = timestamp()
    finished_at: str | None = timestamp()
    heartbeat_at: str | None = timestamp()
    config: dict[str, Any] = Field(description="the whole validated training config the worker runs")
    dynamics: JobDynamics | None = Field(description="null until the job's dynamics ensemble is trained or loaded")


class EventOut(BaseModel):
    id: int
    object: Literal["job.event"]
    created_at: str = timestamp()
    type: str
    message: str
    data: dict[str, Any] | None


class MetricOut(BaseModel):
    id: int
    object: Literal["job.metric"]
    created_at: str = timestamp()
    name: str
    step: int
    value: float


class EvaluationOut(BaseModel):
    id: int
    object: Literal["job.evaluation"]
    created_at: str = timestamp()
    epoch: int
    mean_return: float
    normalized_score: float


class CheckpointOut(BaseModel):
    id: int
    object: Literal["job.checkpoint"]
    created_at: str = timestamp()
    epoch: int
    step: int
    size_bytes: int


class PolicyMetadata(BaseModel):
    """metadata.json beside an exported policy (`GET /policy?format=metadata`), as the trainer wrote it. Policies of
    older runs may lack the fields that are not required."""

    model_config = ConfigDict(extra="allow")
    env: str
    gym_id: str = Field(description="the gymnasium env the policy was evaluated in, e.g. Hopper-v5")
    obs_dim: int
    act_dim: int
    algorithm: Algorithm
    dataset: dict[str, Any] | None = Field(None, description="what it was trained on, kept after the dataset is "
                                           "deleted: `content_hash` (sha256 of its arrays) and `transitions`")
    config: dict[str, Any] = Field(description="the whole training config")
    epochs: int = Field(description="epochs the run trained")
    which: Which | None = None
    epoch: int | None = Field(None, description="the epoch this policy is from")
    normalized_score: float | None = Field(None, description="this policy's evaluation's normalised score")
    selected_by: str | None = Field(None, description="how this policy was chosen")


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
        "config": row.config, "dynamics": row.dynamics,
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
