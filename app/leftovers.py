"""What a killed API process left under DROP_DATA_DIR, removed when the next one starts: a partial upload
(`uploads/*.part`), the validator's unfinished folder (`datasets/*.part`), and the folder of a dataset or job whose
row is gone (killed between a rename and the row's commit, or between a delete's commit and its `rmtree`).

Only what has been untouched for twice `longest_quiet_s`, so another process's live upload is never taken; a folder
with no row is never a live one (a job's folder is made after its row, a dataset's row is committed right after its
folder is renamed in), and the wait covers a worker that lost a deleted job and still writes its stop checkpoint."""
from __future__ import annotations

import logging
import time
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from kernel.ids import is_id
from kernel.models import Dataset, Job
from kernel.settings import Settings
from kernel.storage import remove_tree, upload_dir

from .datasets.service import longest_quiet_s

log = logging.getLogger("drop.api")
ROWS = (("datasets", "ds", Dataset), ("jobs", "job", Job))


def _untouched_since(paths, stale: float) -> list[Path]:
    found = []
    for path in paths:
        try:
            if path.stat().st_mtime < stale:
                found.append(path)
        except FileNotFoundError:  # another process starting at the same time swept it first
            continue
    return found


def _rowless(sessions: sessionmaker[Session], folders: list[Path], model) -> list[Path]:
    by_id = {p.name: p for p in folders}
    ids, known = list(by_id), set()
    with sessions() as s:
        for start in range(0, len(ids), 500):  # under SQLite's limit on bound parameters
            known.update(s.scalars(select(model.id).where(model.id.in_(ids[start:start + 500]))))
    return [p for name, p in by_id.items() if name not in known]


def sweep_abandoned(settings: Settings, sessions: sessionmaker[Session]) -> list[str]:
    """Remove the leftovers, and return their names relative to DROP_DATA_DIR."""
    stale = time.time() - 2 * longest_quiet_s(settings)
    parts = _untouched_since((p for folder in (upload_dir(settings), settings.data_dir / "datasets")
                              for p in folder.glob("*.part")), stale)
    orphans = [p for folder, prefix, model in ROWS
               for p in _rowless(sessions, _untouched_since(
                   (p for p in (settings.data_dir / folder).glob(f"{prefix}_*") if is_id(p.name, prefix)), stale),
                   model)]
    for path in parts + orphans:
        if path.is_dir():
            remove_tree(path)
        else:
            path.unlink(missing_ok=True)
    names = sorted(str(p.relative_to(settings.data_dir)) for p in parts + orphans)
    if names:
        log.info("removed %d leftovers of killed processes: %s", len(names), ", ".join(names))
    return names
