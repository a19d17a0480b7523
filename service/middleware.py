"""Pure ASGI middleware: the streaming request-size limit and the last-resort 500 (issue #16).

``BodySizeLimit`` counts body bytes as they arrive, whatever the transfer encoding (a declared
Content-Length over the limit is refused before reading anything; a chunked body is cut off as soon as
the count passes the limit), so no request makes the server hold more than ``max_bytes`` of body.

``CatchAll`` turns an exception that escaped every handler into a problem+json 500 carrying a
correlation id (also logged with the traceback) and *does not re-raise it*: Starlette's
``ServerErrorMiddleware`` re-raises after answering, and uvicorn then closes the keep-alive connection,
so a client's next request on it failed with a reset.
"""

from __future__ import annotations

import logging
import uuid

from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from common.errors import PayloadTooLargeError
from service.problems import problem_response

log = logging.getLogger("hoi_refine.service")


class _TrackedSend:
    """``send`` that remembers whether the response has started: after that no error answer can replace it."""

    def __init__(self, send: Send) -> None:
        self.started = False
        self._send = send

    async def __call__(self, message: Message) -> None:
        if message["type"] == "http.response.start":
            self.started = True
        await self._send(message)


class BodySizeLimit:
    """413 for a body over ``max_bytes``: at once from Content-Length, else while it streams in."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope["headers"]:
            if name == b"content-length" and value.isdigit() and int(value) > self.max_bytes:
                detail = f"request body is {int(value)} bytes, over the limit of {self.max_bytes}"
                await problem_response(413, "Payload too large", detail)(scope, receive, send)
                return
        received = 0

        async def counting_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    # Raised inside whatever reads the body; the project's handler answers 413.
                    raise PayloadTooLargeError(f"request body is over the limit of {self.max_bytes} bytes")
            return message

        tracked = _TrackedSend(send)
        try:
            await self.app(scope, counting_receive, tracked)
        except PayloadTooLargeError as exc:  # read outside a route (no handler there): answer here
            if tracked.started:
                raise
            await problem_response(413, PayloadTooLargeError.title, str(exc))(scope, receive, send)


class CatchAll:
    """The last-resort 500: logged with a correlation id that the problem body repeats; never re-raised."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        tracked = _TrackedSend(send)
        try:
            await self.app(scope, receive, tracked)
        except Exception as exc:
            correlation_id = uuid.uuid4().hex
            log.error("unhandled error [correlation id %s] %s %s", correlation_id, scope.get("method"),
                      scope.get("path"), exc_info=exc)  # fmt: skip
            if tracked.started:  # the answer is on its way: nothing better to do than end this connection
                raise
            await internal_error(correlation_id)(scope, receive, send)


def internal_error(correlation_id: str) -> JSONResponse:
    detail = f"an unexpected error occurred; it has been logged with correlation id {correlation_id}"
    headers = {"X-Correlation-ID": correlation_id}
    return problem_response(500, "Internal error", detail, headers=headers, extra={"correlation_id": correlation_id})
