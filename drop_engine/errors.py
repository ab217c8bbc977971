"""The engine's errors for bad input, in a module of their own so that every module can raise them and none has to
import another's machinery to catch them. Each message names the key or field and what is wrong with it, because the
service shows it to the person who sent the input."""
from __future__ import annotations


class DatasetError(ValueError):
    """A dataset that cannot be used; the message says which key and why."""


class DatasetTooLarge(DatasetError):
    """A dataset that declares more rows or decoded bytes than the caller's limits; `limit` says which."""

    def __init__(self, message: str, limit: str):
        super().__init__(message)
        self.limit = limit


class ConfigError(ValueError):
    """A configuration that cannot be built; the message names the field."""
