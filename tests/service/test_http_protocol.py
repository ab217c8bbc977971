"""Connections to the API get TCP_NODELAY even on a listening socket uvicorn bound itself (`drop api --workers N`),
whose `proto` of 0 keeps asyncio from setting it: without it every keep-alive request waited 40 ms for a delayed ACK."""
from __future__ import annotations

import asyncio
import socket
import threading
import time

import httpx
import pytest
import uvicorn

from app.serving.http_protocol import IMPORT_PATH


async def _ok(scope, receive, send) -> None:
    if scope["type"] != "http":
        return
    await send({"type": "http.response.start", "status": 200, "headers": [(b"content-type", b"text/plain")]})
    await send({"type": "http.response.body", "body": b"ok"})


@pytest.mark.parametrize(("http", "nodelay"), [("httptools", 0), (IMPORT_PATH, 1)])
def test_connections_on_a_socket_uvicorn_bound(http, nodelay):
    """uvicorn's own protocol on its own bound socket leaves Nagle on (the bug, asserted so a uvicorn that fixes it
    shows up here); the API's protocol turns it off."""
    config = uvicorn.Config(_ok, host="127.0.0.1", port=0, http=http, loop="asyncio", log_config=None,
                            access_log=False, lifespan="off")  # asyncio's loop: the one `drop api` runs
    sock = config.bind_socket()  # as uvicorn's process supervisor does for --workers N
    assert sock.proto == 0
    server = uvicorn.Server(config)
    thread = threading.Thread(target=lambda: asyncio.run(server.serve(sockets=[sock])), daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not server.started:
            assert time.monotonic() < deadline and thread.is_alive(), "the server did not start"
            time.sleep(0.01)
        with httpx.Client(base_url=f"http://127.0.0.1:{sock.getsockname()[1]}") as client:
            assert client.get("/").text == "ok"  # the connection stays open (keep-alive) while it is inspected
            served = [conn.transport.get_extra_info("socket") for conn in server.server_state.connections]
            assert len(served) == 1
            assert served[0].getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) == nodelay
    finally:
        server.should_exit = True
        thread.join(30)
        sock.close()
