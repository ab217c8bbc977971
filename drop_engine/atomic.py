"""Write-then-rename, so a reader never sees half a file and a failed write (a full disk) leaves nothing behind."""
from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary name beside `path` to write to; renamed onto `path` on success, removed on failure."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        yield tmp
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> None:
    """Replace a text file in whole: for files that are read back (a run's summary, its logs cut back on resume)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def save_durably(obj, path: str | Path) -> None:
    """torch.save through a temporary name with fsync before the rename: after a crash the previous file is intact.
    The directory is made if missing."""
    import torch

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        torch.save(obj, handle)
        handle.flush()
        os.fsync(handle.fileno())
