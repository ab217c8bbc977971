"""Where files live under DROP_DATA_DIR; the database stores these paths, workers on other machines share the volume."""
from __future__ import annotations

import shutil
from pathlib import Path

from .ids import is_id
from .settings import Settings


def _id(value: str, prefix: str) -> str:
    """Paths are built from ids only; anything else here is a bug, never a client's string."""
    if not is_id(value, prefix):
        raise ValueError(f"{value!r} is not a {prefix} id")
    return value


def dataset_dir(settings: Settings, dataset_id: str) -> Path:
    return settings.data_dir / "datasets" / _id(dataset_id, "ds")


def job_dir(settings: Settings, job_id: str) -> Path:
    return settings.data_dir / "jobs" / _id(job_id, "job")


def model_cache_dir(settings: Settings) -> Path:
    """Trained dynamics ensembles, shared by every job (and owner) training on the same data with the same seed."""
    return settings.data_dir / "models"


def upload_dir(settings: Settings) -> Path:
    path = settings.data_dir / "uploads"
    path.mkdir(parents=True, exist_ok=True)
    return path


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
