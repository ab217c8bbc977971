"""SQLAlchemy models. The job row is the truth about a job; Celery only carries "run job N"."""
from __future__ import annotations

from datetime import datetime, timezone
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    ColumnElement,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    case,
)
from sqlalchemy.ext.hybrid import hybrid_property
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


# Ids of the tables that grow with every job and are paged by id (events, metrics, evaluations): 64-bit, so they never
# run out and every cursor the API takes is one (migration 0006). On SQLite INTEGER PRIMARY KEY already is the 64-bit
# rowid, and only that spelling counts ids up by itself.
ROW_ID = BigInteger().with_variant(Integer, "sqlite")

class UTCDateTime(TypeDecorator):
    """Timezone-aware UTC on every backend (SQLite stores naive values)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value, dialect):
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=timezone.utc)
        return value

    def process_result_value(self, value, dialect):
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=timezone.utc)
        return value


class Base(DeclarativeBase):
    type_annotation_map = {datetime: UTCDateTime(), dict[str, Any]: JSON, list[Any]: JSON}


class Owner(Base):
    __tablename__ = "owners"
    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class Token(Base):
    __tablename__ = "tokens"
    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    owner_id: Mapped[str] = mapped_column(ForeignKey("owners.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(200))
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    revoked_at: Mapped[datetime | None]


class Dataset(Base):
    __tablename__ = "datasets"
    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    owner_id: Mapped[str] = mapped_column(ForeignKey("owners.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(300))
    format: Mapped[str] = mapped_column(String(20))
    sha256: Mapped[str] = mapped_column(String(64))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    decoded_bytes: Mapped[int] = mapped_column(BigInteger, server_default="0")  # rows x bytes of a transition
    path: Mapped[str] = mapped_column(Text)
    env: Mapped[str | None] = mapped_column(String(50))
    obs_dim: Mapped[int] = mapped_column(Integer)
    act_dim: Mapped[int] = mapped_column(Integer)
    report: Mapped[dict[str, Any]]
    created_at: Mapped[datetime] = mapped_column(default=utcnow)

    @hybrid_property
    def charged_bytes(self) -> int:
        """What the dataset counts toward its owner's storage quota: its file, or what it decodes to if more."""
        return max(self.size_bytes, self.decoded_bytes)

    @charged_bytes.inplace.expression
    @classmethod
    def _charged_bytes(cls) -> ColumnElement[int]:
        return case((cls.decoded_bytes > cls.size_bytes, cls.decoded_bytes), else_=cls.size_bytes)


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = (
        UniqueConstraint("owner_id", "idempotency_key", name="uq_jobs_owner_idempotency_key"),
        Index("ix_jobs_owner_status", "owner_id", "status"),
        Index("ix_jobs_owner_id_id", "owner_id", "id"),
    )
    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    owner_id: Mapped[str] = mapped_column(ForeignKey("owners.id", ondelete="CASCADE"), index=True)
    dataset_id: Mapped[str | None] = mapped_column(ForeignKey("datasets.id", ondelete="SET NULL"), index=True)
    algorithm: Mapped[str] = mapped_column(String(20))
    env: Mapped[str] = mapped_column(String(50))
    preset: Mapped[str] = mapped_column(String(20))
    overrides: Mapped[dict[str, Any]]
    seed: Mapped[int] = mapped_column(Integer)
    config: Mapped[dict[str, Any]]
    # One of kernel.job_state.JobStatus (CHECK ck_jobs_status, migration 0005), changed by job_state.transition alone.
    status: Mapped[str] = mapped_column(String(20), default="queued")
    progress: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    latest_metrics: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    best_score: Mapped[float | None] = mapped_column(Float)
    last_score: Mapped[float | None] = mapped_column(Float)
    best_epoch: Mapped[int | None] = mapped_column(Integer)
    final_score: Mapped[float | None] = mapped_column(Float)
    # The ensemble the run trains on (Callback.on_dynamics, less the server's path to it): migration 0009.
    dynamics: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    error_code: Mapped[str | None] = mapped_column(String(50))
    error_message: Mapped[str | None] = mapped_column(Text)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer)
    max_runtime_s: Mapped[int] = mapped_column(Integer)
    worker: Mapped[str | None] = mapped_column(String(200))
    heartbeat_at: Mapped[datetime | None]
    enqueued_at: Mapped[datetime | None]
    idempotency_key: Mapped[str | None] = mapped_column(String(200))
    request_hash: Mapped[str | None] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    queue_wait_s: Mapped[float | None] = mapped_column(Float)  # created to first claimed
    run_s: Mapped[float | None] = mapped_column(Float)  # what its finished and handed-back attempts ran
    dynamics_from_cache: Mapped[bool | None]


class DeletedJob(Base):
    """What /metrics counts of a job that was deleted (its attempts, timings and model-cache use), so the counters it
    aggregates from the job rows never go down when a job goes (migration 0007)."""
    __tablename__ = "deleted_jobs"
    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    attempts: Mapped[int] = mapped_column(Integer)
    queue_wait_s: Mapped[float | None] = mapped_column(Float)
    run_s: Mapped[float | None] = mapped_column(Float)
    dynamics_from_cache: Mapped[bool | None]
    deleted_at: Mapped[datetime] = mapped_column(default=utcnow)


class DeletedDataset(Base):
    """A dataset whose row is gone and whose folder may not be: written in the delete's transaction and removed once
    the folder is, so the next API start removes the folder of a process killed in between (migration 0008)."""
    __tablename__ = "deleted_datasets"
    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    deleted_at: Mapped[datetime] = mapped_column(default=utcnow)


class JobEvent(Base):
    __tablename__ = "job_events"
    __table_args__ = (Index("ix_job_events_job_id_id", "job_id", "id"),)
    id: Mapped[int] = mapped_column(ROW_ID, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    type: Mapped[str] = mapped_column(String(30))
    message: Mapped[str] = mapped_column(Text, default="")
    data: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class JobMetric(Base):
    __tablename__ = "job_metrics"
    __table_args__ = (Index("ix_job_metrics_job_name_step", "job_id", "name", "step"),)
    id: Mapped[int] = mapped_column(ROW_ID, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(100))
    step: Mapped[int] = mapped_column(Integer)
    value: Mapped[float] = mapped_column(Float)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class JobEvaluation(Base):
    __tablename__ = "job_evaluations"
    id: Mapped[int] = mapped_column(ROW_ID, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    epoch: Mapped[int] = mapped_column(Integer)
    mean_return: Mapped[float] = mapped_column(Float)
    normalized_score: Mapped[float] = mapped_column(Float)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)


class JobCheckpoint(Base):
    __tablename__ = "job_checkpoints"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    epoch: Mapped[int] = mapped_column(Integer)
    step: Mapped[int] = mapped_column(Integer)
    path: Mapped[str] = mapped_column(Text)
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    created_at: Mapped[datetime] = mapped_column(default=utcnow)
