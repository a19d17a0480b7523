"""``GET /v1/jobs/{id}``: the status poll, the API's hottest path, kept lean (issue #20 item 3).

Clients poll this every couple of seconds per job, so its cost bounds how many jobs a server can watch.
It skips FastAPI's dependency solving (auth, settings and the query check are read straight off the
request, the key through the same in-process cache), and it versions the representation by the job's
``updated_at``, which every write to a job sets. A poll of an unchanged job is one small indexed read
(owner, ``updated_at``) and then either a 304 (``If-None-Match`` matched) or the body this process
serialised last time (``RepresentationCache``, keyed by job and checked against ``updated_at``, so it is
never stale, even with several API processes). Only a changed or first poll reads the full row with its
result summary and serialises it.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from typing import Any

from fastapi import APIRouter, Request, Response
from starlette.concurrency import run_in_threadpool

from common.errors import FieldProblem, InvalidRequestError
from common.job_state import ACTIVE
from common.queue import JobQueue
from common.settings import Settings
from service.deps import bearer_token, key_id_for
from service.routes.jobs import COMMON_ERRORS
from service.schemas import JobPublic

#: Bump when ``JobPublic``'s JSON changes shape, so ETags issued by an older server stop matching.
REPRESENTATION_VERSION = "3"

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], responses=COMMON_ERRORS)


class RepresentationCache:
    """The last serialised body per job (LRU, bounded), valid while the job's ``updated_at`` is unchanged."""

    def __init__(self, max_entries: int = 4096) -> None:
        self.max_entries = max_entries
        self._entries: OrderedDict[str, tuple[str, bytes, str]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, job_id: str, version: str) -> tuple[bytes, str] | None:
        """(body, state) when the cached body is of this version (the caller has checked the owner)."""
        with self._lock:
            hit = self._entries.get(job_id)
            if hit is None or hit[0] != version:
                return None
            self._entries.move_to_end(job_id)
            return hit[1], hit[2]

    def put(self, job_id: str, version: str, body: bytes, state: str) -> None:
        with self._lock:
            self._entries[job_id] = (version, body, state)
            self._entries.move_to_end(job_id)
            while len(self._entries) > self.max_entries:
                self._entries.popitem(last=False)


def etag_for(job_id: str, version: str, settings: Settings) -> str:
    # max_attempts comes from the server's settings, not the row: part of the version too.
    raw = f"{job_id}|{version}|{settings.max_attempts}|{REPRESENTATION_VERSION}"
    return f'"{hashlib.sha256(raw.encode()).hexdigest()[:32]}"'


def _matches(if_none_match: str | None, etag: str) -> bool:
    if if_none_match is None:
        return False
    tags = [t.strip().removeprefix("W/") for t in if_none_match.split(",")]
    return etag in tags or "*" in tags


@router.get(
    "/{job_id}",
    response_model=JobPublic,
    summary="A job's state, attempt, progress and (when done) summary metrics",
    responses={304: {"description": "Not modified (If-None-Match matched the ETag)"}},
    openapi_extra={
        "parameters": [{"name": "If-None-Match", "in": "header", "required": False, "schema": {"type": "string"}}],
        "security": [{"HTTPBearer": []}],
    },
)
async def get_job(job_id: str, request: Request) -> Any:
    if request.query_params:
        names = sorted(set(request.query_params))
        raise InvalidRequestError([FieldProblem(n or "(empty name)", "is not a parameter of this endpoint")
                                   for n in names])  # fmt: skip
    queue: JobQueue = request.app.state.queue
    settings: Settings = request.app.state.settings
    cache: RepresentationCache = request.app.state.job_cache
    key_id = await key_id_for(request, bearer_token(request))
    version = await run_in_threadpool(queue.version, key_id, job_id)
    etag = etag_for(job_id, version, settings)
    cached = cache.get(job_id, version)
    if _matches(request.headers.get("if-none-match"), etag):
        state = cached[1] if cached is not None else None
        return Response(status_code=304, headers={"ETag": etag, **_retry_after(state, settings)})
    if cached is not None:
        body, state = cached
    else:
        # A write between the version read and this one only makes the body newer than its ETag: the next
        # poll sees another version and reads again, so nothing stale is ever served as current.
        job = await run_in_threadpool(queue.get, key_id, job_id)
        body, state = JobPublic.from_record(job).model_dump_json().encode(), job.state
        cache.put(job.id, version, body, state)
    return Response(body, media_type="application/json", headers={"ETag": etag, **_retry_after(state, settings)})


def _retry_after(state: str | None, settings: Settings) -> dict[str, str]:
    """Retry-After (the polling interval) while the job is unfinished; an unchanged job (304, ``state``
    None) keeps the state it had, and a client polls a finished job no more, so it gets one too."""
    if state is None or state in ACTIVE:
        return {"Retry-After": str(settings.poll_retry_after_seconds)}
    return {}
