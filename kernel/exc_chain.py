"""Walk an exception's causes: libraries wrap errors in their own (torch.save turns ENOSPC into a RuntimeError, a
database driver raises its own error while a time limit interrupts it), and what matters is often inside."""
from __future__ import annotations

from typing import Iterator


def causes(exc: BaseException | None) -> Iterator[BaseException]:
    """`exc`, then what it was raised from or while handling, and so on."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__
