"""Request-scoped dependencies: settings, a database session, the owner, and the `?after=` cursors of lists."""
from __future__ import annotations

from typing import Annotated, Iterator

from fastapi import Depends, Query, Request
from sqlalchemy.orm import Session

from kernel.ids import id_pattern
from kernel.settings import Settings

from .auth import current_owner


def settings(request: Request) -> Settings:
    return request.app.state.settings


def session(request: Request) -> Iterator[Session]:
    with request.app.state.sessions() as s:
        yield s


def _cursor(prefix: str):
    """The type of a list's `?after=`: an id, as the previous page's `next_after` gave it; anything else is a 422."""
    return Annotated[str | None, Query(pattern=id_pattern(prefix), description="`next_after` of the previous page")]


DatasetCursor = _cursor("ds")
JobCursor = _cursor("job")
OwnerId = Annotated[str, Depends(current_owner)]
# Closed as soon as the endpoint returns, before the response is sent: a streamed response (the event stream) must
# not keep a pooled connection for its whole life.
DbSession = Annotated[Session, Depends(session, scope="function")]
AppSettings = Annotated[Settings, Depends(settings)]
