"""The FastAPI application: ``create_app()`` wires the queue, the API keys, the routes, problem handlers, limits.

``uvicorn --factory service.app:create_app`` (what ``hoi-refine serve`` runs) or ``create_app(settings,
engine)`` in tests. The database must already be at the migration head (``serve`` upgrades it first;
``/readyz`` says when it is not).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from sqlalchemy.engine import Engine

from common.api_key_store import ApiKeyStore
from common.database import create_engine_for
from common.queue import JobQueue
from common.settings import Settings, get_settings
from common.webhook_store import WebhookStore
from service.metrics import make_registry
from service.middleware import BodySizeLimit, CatchAll
from service.problems import install_problem_handlers
from service.routes import artifacts, batches, dashboard, job_status, jobs, ops, webhooks
from service.schemas import JobCreate
from service.webhook_dispatcher import WebhookDispatcher

API_VERSION = "1.0.0"
DESCRIPTION = (
    "Physics-in-the-loop refinement of hand-object demonstrations, as a job queue. Submit a sequence (a hand and "
    "an object pose per frame) to `POST /v1/jobs`; a worker drives an articulated hand in MuJoCo, lets the object "
    "move only through contact, and optimises the hand's motion until the simulated object follows the recorded "
    "one. A job that ran to the end is SUCCEEDED; its `outcome` says whether the refined sequence is executable "
    "(every frame from 10 on within 3 cm / 30 deg of the recorded object) and, when not, why. Every job and batch "
    "body links its result, contacts, metrics, events, input and files. Authenticate with `Authorization: Bearer "
    "KEY` (`hoi-refine keys create NAME`); errors are `application/problem+json` naming each field."
)


def create_app(settings: Settings | None = None, engine: Engine | None = None) -> FastAPI:
    settings = settings if settings is not None else get_settings()
    owns_engine = engine is None
    # No pre-ping on the API's pool: it would add a round trip to every request (the status poll is one
    # short read). After a database restart the first request on a dead connection answers 503 and the
    # pool drops its connections, so the next one reconnects.
    engine = engine if engine is not None else create_engine_for(settings.resolved_database_url(), pool_pre_ping=False)
    queue = JobQueue(engine, settings)

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        dispatcher = WebhookDispatcher(_app.state.webhooks) if settings.webhook_dispatcher else None
        task = asyncio.create_task(dispatcher.run()) if dispatcher is not None else None
        _app.state.webhook_dispatcher = dispatcher
        try:
            yield
        finally:
            if dispatcher is not None and task is not None:
                dispatcher.stop()
                await task
            if owns_engine:
                engine.dispose()

    app = FastAPI(
        title="hoi-refine",
        version=API_VERSION,
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.engine = engine
    app.state.queue = queue
    app.state.api_keys = ApiKeyStore(engine)
    app.state.webhooks = WebhookStore(engine, settings)
    app.state.key_cache = {}
    app.state.job_cache = job_status.RepresentationCache()
    app.state.metrics_registry = make_registry(queue)
    install_problem_handlers(app)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_request_bytes)
    app.add_middleware(CatchAll)  # added last: the outermost of ours, so it sees every escaped exception
    app.include_router(job_status.router)
    app.include_router(jobs.router)
    app.include_router(artifacts.router)
    app.include_router(batches.router)
    app.include_router(webhooks.router)
    app.include_router(ops.router)
    app.include_router(dashboard.router)
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]
    return app


def _openapi(app: FastAPI) -> dict[str, Any]:
    """The generated schema plus ``JobCreate``, which the JSON/multipart submit route reads by hand."""
    if app.openapi_schema is None:
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        job_create = JobCreate.model_json_schema(ref_template="#/components/schemas/{model}")
        components.update(job_create.pop("$defs", {}))
        components["JobCreate"] = job_create
        app.openapi_schema = schema
    return app.openapi_schema
