"""RFC 9457 problem+json for every error, so clients get one shape and never a stack trace."""
from __future__ import annotations

import logging
from http import HTTPStatus
from typing import Annotated, Any, get_args

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidatorFunctionWrapHandler, WrapValidator
from pydantic_core import PydanticCustomError
from starlette.exceptions import HTTPException as StarletteHTTPException
from typing_extensions import TypeAliasType

from kernel.storage_errors import storage_failure

log = logging.getLogger("drop.api")
MEDIA_TYPE = "application/problem+json"


class Problem(Exception):
    """Raise anywhere in a request to answer with problem+json."""

    def __init__(self, status: int, code: str, detail: str, headers: dict[str, str] | None = None, **extra):
        super().__init__(detail)
        self.status, self.code, self.detail, self.headers, self.extra = status, code, detail, headers, extra


def problem_response(status: int, code: str, detail: str, headers: dict | None = None, **extra) -> JSONResponse:
    body = {
        "type": f"urn:drop-rl:problem:{code}",
        "title": HTTPStatus(status).phrase,
        "status": status,
        "detail": detail,
        "code": code,
        **extra,
    }
    return JSONResponse(body, status_code=status, media_type=MEDIA_TYPE, headers=headers)


class FieldError(BaseModel):
    field: str
    message: str
    limit: int | None = Field(None, description="the server's limit the value exceeds (code job_over_limit)")


class ProblemBody(BaseModel):
    """An error: RFC 9457 problem details plus a stable `code`; `errors` names the bad fields of a 422."""

    model_config = ConfigDict(extra="allow", title="Problem")
    type: str
    title: str
    status: int
    detail: str
    code: str
    errors: list[FieldError] | None = None


def _document_problems(spec: dict) -> None:
    """Every 4xx and 5xx answer of every operation is problem+json, in place of FastAPI's own 422 shape."""
    schemas = spec.setdefault("components", {}).setdefault("schemas", {})
    problem = ProblemBody.model_json_schema(ref_template="#/components/schemas/{model}")
    schemas.update(problem.pop("$defs", {}))
    schemas["Problem"] = problem
    for name in ("HTTPValidationError", "ValidationError"):
        schemas.pop(name, None)
    answer = {"description": "Error (application/problem+json)",
              "content": {MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}}}
    for operations in spec.get("paths", {}).values():
        for operation in operations.values():
            operation["responses"].pop("422", None)
            operation["responses"].update({"4XX": answer, "5XX": answer})


_CODES = {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found", 405: "method_not_allowed",
          406: "not_acceptable", 409: "conflict", 413: "payload_too_large", 415: "unsupported_media_type",
          422: "validation_error", 429: "too_many_requests"}


def one_of(choices: TypeAliasType, code: str) -> Any:
    """The type `choices` (a named Literal of strings) for a request field whose other strings are refused with
    problem code `code` (e.g. unknown_algorithm) rather than validation_error, and a message that lists the choices."""
    allowed = ", ".join(get_args(choices.__value__))

    def check(value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        try:
            return handler(value)
        except ValidationError:
            if not isinstance(value, str):
                raise  # not a string at all: the usual type error
            raise PydanticCustomError("one_of", "{message}", {"message": f"{value!r} is not one of {allowed}",
                                                              "problem_code": code}) from None

    return Annotated[choices, WrapValidator(check)]


def _code(exc: RequestValidationError) -> str:
    """A field's own code (see `one_of`) when every bad field has one, the first of them; else validation_error."""
    codes = [(err.get("ctx") or {}).get("problem_code") for err in exc.errors()]
    return codes[0] if codes and all(codes) else "validation_error"


def _field_errors(exc: RequestValidationError) -> list[dict]:
    out = []
    for err in exc.errors():
        loc = [str(p) for p in err.get("loc", ()) if p != "body"]
        out.append({"field": ".".join(loc) or "body", "message": err.get("msg", "invalid")})
    return out


def _unreadable_body(exc: RequestValidationError) -> Problem | None:
    """A body that is not JSON at all, which pydantic reports as a field named by a character offset (invalid JSON) or
    as the whole body being no object (JSON sent without its Content-Type, curl -d's default): said as what it is."""
    for err in exc.errors():
        loc = tuple(err.get("loc", ()))
        if err.get("type") == "json_invalid":
            reason = (err.get("ctx") or {}).get("error", "malformed")
            return Problem(400, "invalid_json",
                           f"the request body is not valid JSON: {reason} (at character {loc[-1]})")
        if loc == ("body",) and isinstance(err.get("input"), bytes):
            return Problem(415, "unsupported_media_type",
                           "the request body must be JSON sent with the header Content-Type: application/json")
    return None


def install(app: FastAPI) -> None:
    generate = app.openapi

    def openapi() -> dict:
        if app.openapi_schema is None:
            _document_problems(generate())  # FastAPI caches the schema it generates; amend it once
        return app.openapi_schema

    app.openapi = openapi

    @app.exception_handler(Problem)
    async def _problem(_: Request, exc: Problem):
        return problem_response(exc.status, exc.code, exc.detail, headers=exc.headers, **exc.extra)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException):
        detail = exc.detail if isinstance(exc.detail, str) else HTTPStatus(exc.status_code).phrase
        if exc.status_code == 404 and detail == "Not Found":
            detail = "no such resource"
        return problem_response(exc.status_code, _CODES.get(exc.status_code, "error"), detail,
                                headers=getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        if unreadable := _unreadable_body(exc):
            return await _problem(request, unreadable)
        errors = _field_errors(exc)
        detail = "; ".join(f"{e['field']}: {e['message']}" for e in errors)
        return problem_response(422, _code(exc), detail, errors=errors)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(500, "internal_error", "the server failed to handle this request; it has been logged")

    @app.exception_handler(OSError)
    async def _storage(request: Request, exc: OSError):
        """A full or read-only disk is the server's state, not a bug: 507 Insufficient Storage, without paths."""
        failure = storage_failure(exc, "the request's data")
        if failure is None:
            return await _unexpected(request, exc)
        log.error("storage failure on %s %s: %s", request.method, request.url.path, exc)
        return problem_response(507, *failure)
