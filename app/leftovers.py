"""What a killed API process left under DROP_DATA_DIR, removed when the next one starts: a partial upload
(`uploads/*.part`), the validator's unfinished folder (`datasets/*.part`), and the folder of a job or a dataset deleted
by a process killed between the delete's commit and its `rmtree`.

Only what has been untouched for twice `longest_quiet_s`, so another process's live upload is never taken, except a
deleted dataset's folder, which nothing writes again. A job's or a dataset's folder goes only when `deleted_jobs` or
`deleted_datasets` records its deletion, never for want of a row: an API started on the wrong database (another
`DATABASE_URL`, a restored backup) must not take every folder it has no row for. A worker that lost a deleted job and
still writes its stop checkpoint removes the folder itself (worker/runner.py)."""
from __future__ import annotations

import logging
import time
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from kernel.ids import is_id
from kernel.models import DeletedDataset, DeletedJob
from kernel.settings import Settings
from kernel.storage import remove_tree, upload_dir

from .datasets.service import longest_quiet_s, remove_deleted_folders

log = logging.getLogger("drop.api")


def _untouched_since(paths, stale: float) -> list[Path]:
    found = []
    for path in paths:
        try:
            if path.stat().st_mtime < stale:
                found.append(path)
        except FileNotFoundError:  # another process starting at the same time swept it first
            continue
    return found


def _deleted_jobs(sessions: sessionmaker[Session], folders: list[Path]) -> list[Path]:
    by_id = {p.name: p for p in folders}
    ids, deleted = list(by_id), set()
    with sessions() as s:
        for start in range(0, len(ids), 500):  # under SQLite's limit on bound parameters
            deleted.update(s.scalars(select(DeletedJob.id).where(DeletedJob.id.in_(ids[start:start + 500]))))
    return [p for name, p in by_id.items() if name in deleted]


def _deleted_datasets(settings: Settings, sessions: sessionmaker[Session]) -> list[Path]:
    with sessions() as s:
        return remove_deleted_folders(s, settings, list(s.scalars(select(DeletedDataset.id))))


def sweep_abandoned(settings: Settings, sessions: sessionmaker[Session]) -> list[str]:
    """Remove the leftovers, and return their names relative to DROP_DATA_DIR."""
    stale = time.time() - 2 * longest_quiet_s(settings)
    parts = _untouched_since((p for folder in (upload_dir(settings), settings.data_dir / "datasets")
                              for p in folder.glob("*.part")), stale)
    jobs = _deleted_jobs(sessions, _untouched_since(
        (p for p in (settings.data_dir / "jobs").glob("job_*") if is_id(p.name, "job")), stale))
    for path in parts + jobs:
        if path.is_dir():
            remove_tree(path)
        else:
            path.unlink(missing_ok=True)
    datasets = _deleted_datasets(settings, sessions)
    names = sorted(str(p.relative_to(settings.data_dir)) for p in parts + jobs + datasets)
    if names:
        log.info("removed %d leftovers of killed processes: %s", len(names), ", ".join(names))
    return names
