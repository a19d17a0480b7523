"""Server-sent events over the ``job_events`` log (issue #20 item 2): ``text/event-stream`` framing and the
polling loop behind ``GET /v1/jobs/{id}/events`` and ``GET /v1/batches/{id}/events``.

The stream reads the database every ``events_poll_seconds`` (in a worker thread, one short read
transaction), sends each new event with ``id: <event id>`` so a reconnecting client's ``Last-Event-ID``
resumes right after it, sends a ``: keep-alive`` comment when idle for ``events_heartbeat_seconds``, and
ends once the job (or every job of the batch) is finished and its events are out, or after
``events_max_seconds`` (the client reconnects and loses nothing).
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

from starlette.concurrency import run_in_threadpool
from starlette.requests import Request

from common.errors import FieldProblem, InvalidRequestError
from common.queue import EVENTS_PER_READ
from common.queue_types import JobEventRecord
from common.settings import Settings
from common.webhook_store import EVENT_TYPES

MEDIA_TYPE = "text/event-stream"
#: Sent first: how long a client waits before reconnecting after the stream drops (ms, SSE ``retry:``).
RETRY_MS = 2000

#: ``read(after_id) -> (finished, new events, closing snapshot)``: one poll of the stream's source.
Reader = Callable[[int], tuple[bool, list[JobEventRecord], dict[str, Any]]]


def wants_stream(request: Request) -> bool:
    return MEDIA_TYPE in request.headers.get("accept", "")


def last_event_id(request: Request) -> int:
    """The ``Last-Event-ID`` header (the browser's EventSource sends it on reconnect), 0 when absent."""
    raw = request.headers.get("last-event-id", "").strip()
    if not raw:
        return 0
    if not raw.isdigit():
        raise InvalidRequestError([FieldProblem("Last-Event-ID", "must be an event id this stream sent")])
    return int(raw)


def event_data(event: JobEventRecord) -> dict[str, Any]:
    """What one ``job_events`` row says to a client: the state it entered, progress, and the details."""
    data: dict[str, Any] = {"job_id": event.job_id, "kind": event.kind, "at": event.at.isoformat()}
    if event.kind in EVENT_TYPES:
        data["state"] = EVENT_TYPES[event.kind].removeprefix("job.").upper()
    if event.kind == "progress":
        data["progress"] = event.detail.get("progress", {})
    else:
        data["detail"] = event.detail
    return data


def frame(data: dict[str, Any], event: str, event_id: int | None = None) -> bytes:
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n".encode()


def sse_name(kind: str) -> str:
    return "state" if kind in EVENT_TYPES else "progress" if kind == "progress" else "job"


async def stream(
    request: Request, settings: Settings, read: Reader, after_id: int, end_event: str
) -> AsyncIterator[bytes]:
    """The body of an event-stream response (see the module docstring)."""
    yield f"retry: {RETRY_MS}\n\n".encode()
    started = last_sent = time.monotonic()
    while True:
        finished, events, snapshot = await run_in_threadpool(read, after_id)
        for event in events:
            after_id = event.id
            yield frame(event_data(event), sse_name(event.kind), event.id)
        now = time.monotonic()
        if events:
            last_sent = now
            if len(events) >= EVENTS_PER_READ:
                continue  # more are waiting: read again at once
        if finished:
            yield frame(snapshot, end_event)  # no id: a resumed stream sends it again, which is right
            return
        if now - started > settings.events_max_seconds or await request.is_disconnected():
            return
        if now - last_sent >= settings.events_heartbeat_seconds:
            last_sent = now
            yield b": keep-alive\n\n"
        await asyncio.sleep(settings.events_poll_seconds)
