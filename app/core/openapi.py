"""What the OpenAPI schema needs beyond what FastAPI infers: readable operation ids, and the schema of a file."""
from __future__ import annotations

from fastapi.routing import APIRoute

BINARY = {"type": "string", "format": "binary"}  # a file's bytes, in a request or a response


def operation_id(route: APIRoute) -> str:
    """The route function's name, hyphenated (`jobs_get_policy` -> `jobs-get-policy`): what a client generated from
    the schema names its functions. The functions are named `<domain>_<verb>[_<what>]` so the ids are unique."""
    return route.name.replace("_", "-")
