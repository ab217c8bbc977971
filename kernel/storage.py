"""Where files live under DROP_DATA_DIR, and how the database stores their paths: relative to it, as workers on other
machines share the volume, possibly mounted elsewhere."""
from __future__ import annotations

import os
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


def to_stored(settings: Settings, path: Path) -> str:
    """`path` as the database keeps it: relative to DROP_DATA_DIR, so that machines mounting the shared volume at
    different paths all find it. Symbolic links are kept (a `jobs/` linked to another disk is still under the data
    dir); a path outside it stays absolute."""
    absolute, root = os.path.abspath(path), os.path.abspath(settings.data_dir)
    return os.path.relpath(absolute, root) if os.path.commonpath([absolute, root]) == root else absolute


def from_stored(settings: Settings, stored: str) -> Path:
    """A stored path on this machine. Rows written before paths were stored relative hold absolute ones, which the
    join keeps as they are."""
    return settings.data_dir / stored


def remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
