"""FastAPI dependencies: the queue, the settings, and the caller's API key (Bearer, checked by ``ApiKeyStore``).

They are ``async`` because FastAPI runs every sync dependency in the thread pool: one hop per dependency
per request. Only the endpoint itself (and an API-key lookup on a cache miss) goes to a thread.
"""

from __future__ import annotations

import time
from typing import Annotated, Any

from fastapi import Depends, Query, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.concurrency import run_in_threadpool

from common.api_key_store import ApiKeyStore, hash_key
from common.errors import AuthenticationError, FieldProblem, InvalidRequestError
from common.queue import PAGE_TOKEN_PATTERN, JobQueue
from common.settings import Settings
from common.webhook_store import WebhookStore

#: Seconds a successful key lookup is remembered in-process. ``hoi-refine keys revoke`` runs in another
#: process and cannot clear this cache, so this bounds how long a revoked key keeps working: short enough
#: for revocation to bite at once in practice, long enough that a client polling every couple of seconds
#: costs about one key lookup per cache period instead of one per request.
KEY_CACHE_SECONDS = 5.0

bearer = HTTPBearer(auto_error=False, description="An API key from `hoi-refine keys create NAME`")


async def get_queue(request: Request) -> JobQueue:
    queue: JobQueue = request.app.state.queue
    return queue


async def get_app_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


QueueDep = Annotated[JobQueue, Depends(get_queue)]


def get_webhooks(request: Request) -> WebhookStore:
    store: WebhookStore = request.app.state.webhooks
    return store


WebhooksDep = Annotated[WebhookStore, Depends(get_webhooks)]
SettingsDep = Annotated[Settings, Depends(get_app_settings)]
#: ``page_token`` of the listings: opaque to clients, but its form is in the schema, and the server accepts every
#: token of that form (each is a keyset position), so a generated client and a validator agree with it.
PageToken = Annotated[
    str | None,
    Query(
        pattern=PAGE_TOKEN_PATTERN,
        max_length=100,
        description="Opaque token issued by the service: the next_page_token of the previous page, passed back "
        "unchanged; omit it for the first page",
    ),
]


async def current_key(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> str:
    """The id of the caller's API key; 401 when the header is missing or the key unknown or revoked."""
    if credentials is None or not credentials.credentials:
        raise AuthenticationError("send an API key as 'Authorization: Bearer <key>'")
    return await key_id_for(request, credentials.credentials)


def bearer_token(request: Request) -> str:
    """The Bearer token of a request read by hand (the status poll skips FastAPI's dependency machinery)."""
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise AuthenticationError("send an API key as 'Authorization: Bearer <key>'")
    return token.strip()


async def key_id_for(request: Request, plaintext: str) -> str:
    """Key lookup through the in-process cache; only a miss goes to the database (in a thread)."""
    digest = hash_key(plaintext)
    cache: dict[str, tuple[str, float]] = request.app.state.key_cache
    hit = cache.get(digest)
    now = time.monotonic()
    if hit is not None and hit[1] > now:
        return hit[0]
    store: ApiKeyStore = request.app.state.api_keys
    key_id = await run_in_threadpool(store.authenticate, plaintext)
    if len(cache) > 10_000:  # bounded: a flood of distinct keys cannot grow it without limit
        cache.clear()
    cache[digest] = (key_id, now + KEY_CACHE_SECONDS)
    return key_id


KeyDep = Annotated[str, Depends(current_key)]


async def reject_unknown_query_parameters(request: Request) -> None:
    """422 for query parameters the endpoint does not have: a typo (``pagesize=``) must not be ignored."""
    route = request.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if dependant is None:
        return
    known = _query_names(dependant)
    unknown = sorted({name for name in request.query_params if name not in known})
    if unknown:
        raise InvalidRequestError([FieldProblem(name or "(empty name)", "is not a parameter of this endpoint")
                                   for name in unknown])  # fmt: skip
    # Every parameter takes one value: FastAPI would silently keep the last of ?a=1&a=2.
    repeated = sorted({name for name in request.query_params if len(request.query_params.getlist(name)) > 1})
    if repeated:
        raise InvalidRequestError([FieldProblem(name, "is given more than once") for name in repeated])


def _query_names(dependant: Any) -> set[str]:
    names = {param.alias for param in dependant.query_params}
    for sub in dependant.dependencies:
        names |= _query_names(sub)
    return names
