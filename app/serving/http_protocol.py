"""uvicorn's httptools protocol with TCP_NODELAY set on every connection it serves.

With `--workers N` uvicorn binds the listening socket itself and leaves its `proto` at 0; accepted sockets inherit
that, and asyncio turns on TCP_NODELAY only for sockets that say IPPROTO_TCP (uvicorn issue 3149). Nagle's algorithm
then holds each response's body until the client's delayed ACK of its headers, 40 ms per keep-alive request: two API
processes answered 362 health checks a second where one answered 3,000 (bench/NOTES.md). Setting the option per
connection covers every way uvicorn gets its socket.
"""
from __future__ import annotations

import asyncio
import contextlib
import socket

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

IMPORT_PATH = f"{__name__}:NoDelayHttpToolsProtocol"  # uvicorn's `http` option, importable in every API process


class NoDelayHttpToolsProtocol(HttpToolsProtocol):
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        sock = transport.get_extra_info("socket")
        if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
            with contextlib.suppress(OSError):  # a peer already gone: the connection's own code handles that
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        super().connection_made(transport)
