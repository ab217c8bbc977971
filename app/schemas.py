"""The shapes of successful responses, so the OpenAPI schema tells clients (and the schema fuzz test) exactly what comes
back. `app/serialize.py` builds these objects from rows; FastAPI checks them against these models on the way out."""
from __future__ import annotations

from typing import Any, Generic, Literal, TypeVar

from pydantic import BaseModel, Field

from drop_engine.scores import FINAL_WINDOW

from kernel.job_state import JobStatus

Item = TypeVar("Item")


def timestamp() -> Any:
    return Field(json_schema_extra={"format": "date-time"}, description="RFC 3339, UTC")


class DatasetOut(BaseModel):
    id: str
    object: Literal["dataset"]
    created_at: str = timestamp()
    name: str
    format: str = Field(description="hdf5 | npz | minari")
    size_bytes: int
    decoded_bytes: int = Field(description="rows x bytes of a float32 transition: what it takes once loaded; it counts "
                                           "toward the storage quota when larger than size_bytes")
    sha256: str
    env: str | None = Field(description="the env the dataset's dimensions match, if exactly one")
    obs_dim: int
    act_dim: int
    report: dict[str, Any] = Field(description="what validation found: sizes, episodes, returns, warnings")


class JobError(BaseModel):
    code: str
    message: str | None


class JobOut(BaseModel):
    id: str
    object: Literal["job"]
    created_at: str = timestamp()
    status: Literal[tuple(s.value for s in JobStatus)]  # type: ignore[valid-type]
    dataset_id: str | None = Field(description="null once the dataset is deleted")
    algorithm: str
    env: str
    preset: str
    overrides: dict[str, Any]
    seed: int
    progress: dict[str, Any] | None
    latest_metrics: dict[str, Any] | None
    best_score: float | None = Field(description="the highest normalised score of any evaluation so far")
    last_score: float | None = Field(description="the normalised score of the latest evaluation")
    best_epoch: int | None = Field(description="the epoch of best_score (the earlier of ties): the `which=best` policy's")
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


class Page(BaseModel, Generic[Item]):
    object: Literal["list"]
    data: list[Item]
    has_more: bool
    next_after: str | int | None = Field(description="pass as `after` for the next page; null on the last")


class Status(BaseModel):
    status: str
