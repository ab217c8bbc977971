"""An exclusive `flock` on a lock file, for the directories that several processes may write at once (the model
cache, a collection's output). Lock files are never removed: removing one would let two processes hold "the" lock on
different files. `fcntl` is imported in the call, so the engine runs where POSIX locks do not exist until one is
needed."""
from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from .stopping import StopFlag, check

POLL_S = 0.5


class Busy(RuntimeError):
    """Another process holds the lock and the caller chose not to wait."""


@contextmanager
def exclusive(path: str | Path, should_stop: StopFlag | None = None, busy: str | None = None) -> Iterator[None]:
    """Hold the lock at `path` (its directory is made). With `should_stop`, wait for it, polling so that the waiter can
    still be cancelled (`Stopped`); without, raise `Busy` at once if another process has it, with the caller's `busy`
    message when given (it knows what the lock guards)."""
    import fcntl

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as handle:
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if should_stop is None:
                    raise Busy(busy or f"{path} is held by another process") from None
                check(should_stop)
                time.sleep(POLL_S)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
