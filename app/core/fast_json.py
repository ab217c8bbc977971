"""The hot reads' JSON bodies, written by orjson (Rust) instead of the standard library's encoder.

A job's dict (its config, progress and metrics) took 37 µs through Starlette's `json.dumps`, 3.9 through
`pydantic_core.to_json` and 1.3 through `orjson.dumps` (bench/NOTES.md); a page of 20 jobs twenty times that. orjson
also writes an `orjson.Fragment` as the JSON text it holds: on PostgreSQL the hot reads hand back stored JSON columns
that way (kernel/fast_reads.py), so a job's config is never parsed only to be written out again (8.8 µs a job). NaN
and infinities are written as null, where Starlette's encoder raised and the client got a 500. What orjson refuses
(an integer beyond 64 bits in a JSON column that SQLite parsed) goes through pydantic-core, which writes it. That
path never meets a fragment, which pydantic-core could not write: fragments come only from PostgreSQL's hot reads,
whose other values are typed columns orjson writes (64-bit integers, floats, text, timestamps made strings).
"""
from __future__ import annotations

from typing import Any

import orjson
import pydantic_core
from fastapi.responses import JSONResponse


def dumps(content: Any) -> bytes:
    try:
        return orjson.dumps(content)
    except TypeError:  # orjson.JSONEncodeError is one
        return pydantic_core.to_json(content, inf_nan_mode="null")


class FastJSONResponse(JSONResponse):
    def render(self, content: Any) -> bytes:
        return dumps(content)
