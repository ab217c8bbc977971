"""Public ids: a type prefix plus a time-ordered hex body, so sorting by id is sorting by creation (cursor paging)."""
from __future__ import annotations

import re
import secrets
import time


def new_id(prefix: str) -> str:
    return f"{prefix}_{time.time_ns() // 1000:014x}{secrets.token_hex(4)}"


def id_pattern(prefix: str) -> str:
    """The shape `new_id` gives, as a regular expression for the whole string."""
    return rf"^{prefix}_[0-9a-f]{{1,36}}$"


def is_id(value: str, prefix: str) -> bool:
    """Whether `value` has the shape `new_id` gives: the only strings that may name a file or reach a query."""
    return re.fullmatch(id_pattern(prefix), value) is not None
