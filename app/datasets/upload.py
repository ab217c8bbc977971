"""Stream an upload (raw body or multipart) to one file on disk while hashing it and enforcing the size limit.

Nothing is held in memory beyond one chunk, and the file is removed if anything goes wrong.
"""
from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from fastapi import Request
from python_multipart.multipart import MultipartParser, parse_options_header

from ..core.openapi import BINARY
from ..core.problems import Problem

MULTIPART_SLACK = 64 * 1024  # headers and boundaries around the file part
CONTROL_CHARS = re.compile(r"[\x00-\x1f\x7f]")
# The bodies `receive` reads, for the OpenAPI schema: the endpoint streams its body itself, so FastAPI cannot see them.
REQUEST_BODY = {"required": True, "content": {
    "multipart/form-data": {"schema": {"type": "object", "required": ["file"], "properties": {"file": {
        **BINARY, "description": "the dataset file; its filename names the dataset unless `name` is given"}}}},
    "application/octet-stream": {"schema": BINARY},
}}


@dataclass
class Upload:
    path: Path
    filename: str
    size: int
    sha256: str


class _Sink:
    def __init__(self, path: Path, limit: int, too_large: Callable[[], Problem]):
        self.handle = open(path, "wb")
        self.digest = hashlib.sha256()
        self.size = 0
        self.limit, self.too_large = limit, too_large

    def write(self, data: bytes) -> None:
        self.size += len(data)
        if self.size > self.limit:
            raise self.too_large()
        self.digest.update(data)
        self.handle.write(data)

    def close(self) -> None:
        self.handle.close()


def _too_large(limit: int) -> Problem:
    return Problem(413, "payload_too_large", f"the upload exceeds the limit of {limit} bytes (DROP_MAX_UPLOAD_BYTES)")


def _disposition(value: bytes) -> tuple[str | None, str | None]:
    kind, params = parse_options_header(value)
    name = params.get(b"name")
    filename = params.get(b"filename")
    return (name.decode("utf-8", "replace") if name is not None else None,
            filename.decode("utf-8", "replace") if filename is not None else None)


def _label(text: str) -> str:
    """A dataset's name is only a label (files are named by ids), but NUL and other control characters can be neither
    stored nor shown safely."""
    if CONTROL_CHARS.search(text):
        raise Problem(422, "invalid_name", f"name: {text[:100]!r} contains control characters (such as NUL); "
                      "use a plain name")
    return text


async def _multipart(request: Request, boundary: bytes, sink: _Sink) -> str:
    state = {"field": b"", "value": b"", "headers": {}, "in_file": False, "found": False, "filename": "upload"}

    def on_header_field(data: bytes, start: int, end: int) -> None:
        state["field"] += data[start:end]

    def on_header_value(data: bytes, start: int, end: int) -> None:
        state["value"] += data[start:end]

    def on_header_end() -> None:
        state["headers"][state["field"].lower()] = state["value"]
        state["field"], state["value"] = b"", b""

    def on_headers_finished() -> None:
        name, filename = _disposition(state["headers"].get(b"content-disposition", b""))
        state["in_file"] = name == "file" and not state["found"]
        if state["in_file"]:
            state["found"] = True
            state["filename"] = _label(filename) if filename else "upload"

    def on_part_data(data: bytes, start: int, end: int) -> None:
        if state["in_file"]:
            sink.write(data[start:end])

    def on_part_end() -> None:
        state["headers"], state["in_file"] = {}, False

    parser = MultipartParser(boundary, {
        "on_header_field": on_header_field, "on_header_value": on_header_value, "on_header_end": on_header_end,
        "on_headers_finished": on_headers_finished, "on_part_data": on_part_data, "on_part_end": on_part_end,
    })
    received, most = 0, sink.limit + MULTIPART_SLACK  # every part counts: a dropped one still costs time and headers
    try:
        async for chunk in request.stream():
            received += len(chunk)
            if received > most:
                raise sink.too_large()
            parser.write(chunk)
        parser.finalize()
    except (Problem, OSError):  # ours, and the disk's (full, read-only): not the body's fault
        raise
    except Exception as exc:  # the multipart library's own parse errors
        raise Problem(400, "bad_multipart", f"the multipart body cannot be parsed: {exc}") from None
    if not state["found"]:
        raise Problem(422, "missing_file",
                      "the multipart body has no part named 'file' (use `curl -F file=@data.hdf5`)")
    return state["filename"]


async def receive(request: Request, dest: Path, limit: int, name: str | None,
                  too_large: Callable[[], Problem] | None = None) -> Upload:
    """Write the request's file to `dest`; raises Problem (413, 400, 422) and leaves no file behind on failure.

    Past `limit` bytes it raises `too_large()` (default: the DROP_MAX_UPLOAD_BYTES problem), before reading the
    body when Content-Length already says so, else while streaming.
    """
    too_large = too_large or (lambda: _too_large(limit))
    if name is not None:
        _label(name)
    length = request.headers.get("content-length")
    content_type = request.headers.get("content-type", "")
    is_multipart = content_type.lower().startswith("multipart/form-data")
    if length and length.isdigit() and int(length) > limit + (MULTIPART_SLACK if is_multipart else 0):
        raise too_large()
    sink = _Sink(dest, limit, too_large)
    try:
        if is_multipart:
            _, params = parse_options_header(content_type)
            boundary = params.get(b"boundary")
            if not boundary:
                raise Problem(400, "bad_multipart", "multipart/form-data without a boundary")
            filename = await _multipart(request, boundary, sink)
        else:
            async for chunk in request.stream():
                sink.write(chunk)
            filename = "upload"
        if sink.size == 0:
            raise Problem(422, "empty_upload", "the upload is empty")
    except BaseException:
        sink.close()
        dest.unlink(missing_ok=True)
        raise
    sink.close()
    return Upload(dest, name or filename, sink.size, sink.digest.hexdigest())
