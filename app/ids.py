"""Public ids: a type prefix plus a time-ordered hex body, so sorting by id is sorting by creation (cursor paging)."""
from __future__ import annotations

import secrets
import time


def new_id(prefix: str) -> str:
    return f"{prefix}_{time.time_ns() // 1000:014x}{secrets.token_hex(4)}"
