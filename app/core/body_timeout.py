"""An idle timeout on request bodies (DROP_BODY_IDLE_TIMEOUT_S).

A client that stops sending its body part-way (a Content-Length larger than what it sends, or a chunked body that
never ends) would otherwise hold its socket, and an upload's file, for ever: uvicorn bounds only the wait between
requests. Here each wait for the next piece of a body is bounded; past it the request is answered 408 with
`Connection: close`, so the server closes the connection, and an upload removes its partial file as for any failure.
Once the body is complete, waits pass through unbounded: a streamed response waits on `receive` for the client to go.
"""
from __future__ import annotations

import asyncio

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .problems import Problem, problem_response


class BodyStalled(Problem):
    def __init__(self, timeout: float):
        super().__init__(408, "body_timeout", f"no part of the request body arrived for {timeout:g} s "
                         "(DROP_BODY_IDLE_TIMEOUT_S); the connection is closed", headers={"Connection": "close"})


class IdleBody:
    def __init__(self, app: ASGIApp, timeout: float):
        self.app, self.timeout = app, timeout

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        complete = False

        async def bounded() -> Message:
            nonlocal complete
            if complete:
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), self.timeout)
            except asyncio.TimeoutError:
                raise BodyStalled(self.timeout) from None
            complete = message["type"] != "http.request" or not message.get("more_body", False)
            return message

        try:
            await self.app(scope, bounded, send)
        except BodyStalled as exc:  # raised where no exception handler answers it (the JSON body limit reads first)
            await problem_response(exc.status, exc.code, exc.detail, headers=exc.headers)(scope, receive, send)
