"""Token lookups remembered for a few seconds per API process: every request needs its owner, and asking the
database each time was a round trip per request. A revoked token is refused once its entry expires (at most
DROP_TOKEN_CACHE_S later), in every process alike; unknown tokens are never remembered."""
from __future__ import annotations

import time
from typing import Callable


class TokenCache:
    def __init__(self, ttl_s: float, max_entries: int = 10_000, clock: Callable[[], float] = time.monotonic):
        self.ttl_s, self.max_entries, self.clock = ttl_s, max_entries, clock
        self._owners: dict[str, tuple[str, float]] = {}

    def get(self, token_hash: str) -> str | None:
        entry = self._owners.get(token_hash)
        if entry is None or entry[1] <= self.clock():
            return None
        return entry[0]

    def put(self, token_hash: str, owner_id: str) -> None:
        if self.ttl_s <= 0:
            return
        if len(self._owners) >= self.max_entries:  # many live tokens: start over rather than track ages
            self._owners.clear()
        self._owners[token_hash] = (owner_id, self.clock() + self.ttl_s)
