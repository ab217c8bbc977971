"""Service configuration from the environment (prefix DROP_), so one image runs embedded or in production."""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="DROP_", extra="ignore", allow_inf_nan=False)

    data_dir: Path = Field(Path("data"), description="datasets, job runs, trained dynamics models, broker folders, "
                                                "SQLite file")
    database_url: str | None = Field(None, description="default: sqlite:///<data_dir>/drop.db")
    broker_url: str | None = Field(None, description="default: Celery filesystem transport under data_dir")
    queue: str = "drop-jobs"
    max_upload_bytes: int = Field(2 * 1024**3, ge=1)
    max_active_jobs_per_owner: int = Field(20, ge=1, description="queued + running + cancelling jobs; more get 429")
    max_stored_bytes_per_owner: int = Field(20 * 1024**3, ge=1, description="sum of an owner's dataset uploads; 413")
    # Limits on one job, against the engine's estimate (drop_engine/resources.py); past any, creating it is a 422.
    # The defaults admit every preset, `paper` included, on a 2-million-row dataset.
    max_job_memory_bytes: int = Field(8 * 1024**3, ge=1, description="estimated peak memory of one job")
    max_job_disk_bytes: int = Field(10 * 1024**3, ge=1, description="estimated disk of one job's checkpoints")
    max_job_sac_updates: int = Field(5_000_000, ge=1, description="epochs x steps_per_epoch of one job")
    max_job_metric_rows: int = Field(1_000_000, ge=1, description="metric rows one job may record")
    max_job_eval_episodes: int = Field(100, ge=1, description="episodes per evaluation, each a MuJoCo env held open")
    auth_disabled: bool = Field(False, description="single-user local mode: every request is the 'local' owner")
    worker_threads: int | None = Field(None, ge=1, description="torch threads per job")
    worker_concurrency: int = Field(1, ge=1, description="jobs at once per `drop worker`")
    worker_nice: int = Field(10, ge=0, le=19, description="niceness of the processes that train: batch work that "
                             "yields the CPU to an API on the same machine (0 keeps the worker's own)")
    max_attempts: int = Field(3, ge=1)
    max_runtime_s: int = Field(24 * 3600, ge=1, description="default hard limit for one job attempt")
    heartbeat_s: float = Field(10.0, gt=0)
    stale_after_s: float = Field(120.0, gt=0, description="a running job whose heartbeat is older is re-queued")
    reap_every_s: float = Field(30.0, gt=0)
    redeliver_after_s: float = Field(60.0, gt=0, description="a worker idle this long sends again the queued jobs "
                                     "enqueued before it went idle: their message was lost (e.g. Redis restarted)")
    # What one dataset may hold, whatever its file takes on disk (a lazy HDF5 file of a few KB may declare millions
    # of rows): checked against what the file declares before a row is read (issue 15).
    max_dataset_rows: int = Field(5_000_000, ge=1, description="rows of one dataset; more is a 422")
    max_dataset_bytes: int = Field(2 * 1024**3, ge=1, description="decoded size of one dataset (rows x bytes of a "
                                   "float32 transition); more is a 422")
    validate_timeout_s: float = Field(300.0, gt=0)
    validate_memory_bytes: int = Field(1024**3, ge=256 * 1024**2, description="address-space cap of one validator "
                                       "child; it reads a block of rows at a time, so this does not grow with datasets")
    max_concurrent_validations: int = Field(2, ge=1, description="validator children at once per API process; more "
                                            "wait their turn")
    # Requests that hold a socket and a file while their body arrives (issue 15): per API process.
    body_idle_timeout_s: float = Field(30.0, gt=0, description="a request body that sends nothing for this long is "
                                       "answered 408 and its connection closed")
    max_concurrent_uploads: int = Field(16, ge=1, description="uploads in progress (receiving or validating) per API "
                                        "process; more get 429")
    max_uploads_per_owner: int = Field(4, ge=1, description="uploads in progress per owner per API process; more get "
                                       "429")
    cancel_poll_s: float = Field(0.5, ge=0, description="how often a running job checks for cancellation")
    # Observability and API processes (issue 14)
    log_format: Literal["json", "console"] = Field("json", description="JSON lines, or readable ('console', the "
                                                    "default under `drop serve`)")
    log_level: str = Field("INFO", pattern=r"^(?i:debug|info|warning|error|critical)$")
    max_streams_per_owner: int = Field(20, ge=1, description="open event streams per owner per API process; 429 past")
    db_pool_size: int = Field(5, ge=1, le=200, description="PostgreSQL connections of each API process's pool for "
                              "its hot reads (job, jobs, events, dataset); each API process holds up to this many "
                              "beside its ORM pool (5 + 10 overflow) and its event listener")
    token_cache_s: float = Field(5.0, ge=0, le=60, description="how long an API process trusts a token lookup: a "
                                 "revoked token is refused within this; 0 looks up every request")

    @property
    def sqlalchemy_url(self) -> str:
        return self.database_url or f"sqlite:///{(self.data_dir / 'drop.db').resolve()}"

    @property
    def celery_broker_url(self) -> str:
        return self.broker_url or "filesystem://"

    @property
    def is_filesystem_broker(self) -> bool:
        return self.celery_broker_url.startswith("filesystem://")

    def ensure_dirs(self) -> None:
        for sub in ("datasets", "jobs", "models", "uploads", "broker/queue", "broker/processed"):
            (self.data_dir / sub).mkdir(parents=True, exist_ok=True)


@lru_cache
def get_settings() -> Settings:
    return Settings()
