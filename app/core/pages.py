"""What every API object and list shares: RFC 3339 UTC timestamps, and cursor-paged lists (`?after=&limit=`)."""
from __future__ import annotations

from datetime import datetime, timezone
from typing import Any, Generic, Literal, TypeVar

from pydantic import BaseModel, Field

Item = TypeVar("Item")


def iso(value: datetime | None) -> str | None:
    if value is None:
        return None
    if value.tzinfo is None:
        value = value.replace(tzinfo=timezone.utc)
    return value.astimezone(timezone.utc).isoformat().replace("+00:00", "Z")


def timestamp() -> Any:
    """A response model's field holding an `iso` timestamp."""
    return Field(json_schema_extra={"format": "date-time"}, description="RFC 3339, UTC")


class Page(BaseModel, Generic[Item]):
    object: Literal["list"]
    data: list[Item]
    has_more: bool
    next_after: str | int | None = Field(description="pass as `after` for the next page; null on the last")


def fetch_page(s, query, to_dict, limit: int) -> dict:
    """Run an ordered query for one row past the page, which tells whether there is more."""
    rows = list(s.scalars(query.limit(limit + 1)))
    return page([to_dict(r) for r in rows[:limit]], len(rows) > limit)


def page(items: list[dict], has_more: bool) -> dict:
    return {"object": "list", "data": items, "has_more": has_more,
            "next_after": items[-1]["id"] if items and has_more else None}
