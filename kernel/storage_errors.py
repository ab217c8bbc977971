"""Tell a full or read-only DROP_DATA_DIR from other failures, so an upload answers 507 and a job fails with a code
that says what to fix, instead of a 500 or a `training_error`. Libraries wrap the OSError (torch.save raises a
RuntimeError whose context is the ENOSPC), so the whole chain of causes is searched."""
from __future__ import annotations

import errno
import os

from .exc_chain import causes

_FULL = {errno.ENOSPC, errno.EDQUOT}
_UNWRITABLE = {errno.EROFS, errno.EACCES}


def storage_errno(exc: BaseException | None) -> int | None:
    """The errno of the storage failure behind `exc`, or None when it is some other error."""
    return next((e.errno for e in causes(exc) if isinstance(e, OSError) and e.errno in _FULL | _UNWRITABLE), None)


def storage_failure(exc: BaseException, what: str) -> tuple[str, str] | None:
    """(code, message) for a storage failure while writing `what`, else None."""
    number = storage_errno(exc)
    if number is None:
        return None
    if number in _FULL:
        return "storage_full", (f"{what} could not be written: the server's storage is full ({os.strerror(number)}); "
                                "nothing partial was kept, try again once space has been freed")
    return "storage_unwritable", (f"{what} could not be written: the server's storage is not writable "
                                  f"({os.strerror(number)}); nothing partial was kept")
