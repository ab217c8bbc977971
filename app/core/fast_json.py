"""The hot reads' JSON bodies, written by pydantic-core (Rust) instead of the standard library's encoder.

A job's dict (its config, progress and metrics) took 37 µs through Starlette's `json.dumps` and 8 µs through
`pydantic_core.to_json`; a page of 20 jobs twenty times that (bench/NOTES.md). NaN and infinities are written as
null, where Starlette's encoder raised and the client got a 500.
"""
from __future__ import annotations

from typing import Any

import pydantic_core
from fastapi.responses import JSONResponse


class FastJSONResponse(JSONResponse):
    def render(self, content: Any) -> bytes:
        return pydantic_core.to_json(content, inf_nan_mode="null")
