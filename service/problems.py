"""Every error answer is ``application/problem+json`` (RFC 9457), produced here and only here.

Project errors (``common.errors.HoiRefineError``) carry their HTTP status and title; request-validation
errors from FastAPI become 422 with one ``{field, problem}`` per problem; anything unexpected becomes a
500 without internals in the body (``service.middleware.CatchAll``: logged with a correlation id).
"""

from __future__ import annotations

import logging
import uuid
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy import exc as sa_exc
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from common.errors import (
    DatabaseUnavailableError,
    FieldProblem,
    HoiRefineError,
    LimitExceededError,
    SequenceValidationError,
)
from common.safe_text import shown

PROBLEM_JSON = "application/problem+json"
log = logging.getLogger("hoi_refine.service")


def problem_response(
    status: int,
    title: str,
    detail: str | None = None,
    errors: list[FieldProblem] | None = None,
    headers: dict[str, str] | None = None,
    extra: dict[str, Any] | None = None,
) -> JSONResponse:
    body: dict[str, Any] = {"type": "about:blank", "title": title, "status": status}
    if detail:
        body["detail"] = detail
    if errors is not None:
        body["errors"] = [{"field": p.field, "problem": p.problem} for p in errors]
    body.update(extra or {})
    return JSONResponse(body, status_code=status, media_type=PROBLEM_JSON, headers=headers)


def _field_path(loc: tuple[Any, ...] | list[Any]) -> str:
    """FastAPI's ``("body", "hands", 0, "valid")`` -> ``hands[0].valid``; query/header names stay plain."""
    parts = list(loc)
    if parts and parts[0] in ("body", "query", "path", "header"):
        parts = parts[1:]
    out = ""
    for part in parts:
        if part == "[key]":  # pydantic marks a bad dict key this way; the key itself names the field
            continue
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            # A client's own dict keys can appear here (an unknown member): echo them escaped and short.
            text = str(part)
            out += ("." if out else "") + (text if text.isidentifier() or text == "[key]" else shown(text, 40))
    return out or "body"


def validation_problems(errors: Any) -> list[FieldProblem]:
    return [FieldProblem(_field_path(e.get("loc", ())), str(e.get("msg", "is invalid"))) for e in errors]


async def _hoi_refine_error(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, HoiRefineError)
    headers: dict[str, str] = {}
    if isinstance(exc, LimitExceededError) and exc.retry_after is not None:
        headers["Retry-After"] = str(exc.retry_after)
    if exc.http_status == 401:
        headers["WWW-Authenticate"] = "Bearer"
    extra = None
    if exc.http_status >= 500:
        correlation_id = uuid.uuid4().hex
        log.error("request failed [correlation id %s]: %s", correlation_id, exc)
        headers["X-Correlation-ID"] = correlation_id
        extra = {"correlation_id": correlation_id}
    problems = exc.problems if isinstance(exc, SequenceValidationError) else None
    return problem_response(exc.http_status, exc.title, str(exc), problems, headers or None, extra)


async def _request_validation_error(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    problems = validation_problems(exc.errors())
    return problem_response(422, "Invalid request", "; ".join(map(str, problems)), problems)


async def _http_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    headers = dict(exc.headers or {})
    if exc.status_code == 405:
        # Starlette names only the first route that matched the path; list every method the path has.
        headers["Allow"] = ", ".join(_allowed_methods(request))
    return problem_response(exc.status_code, str(exc.detail), None, None, headers or None)


def _allowed_methods(request: Request) -> list[str]:
    methods: set[str] = set()
    for route in request.app.routes:
        match, _ = route.matches({**request.scope, "method": "GET"})
        route_methods = getattr(route, "methods", None)
        if match != Match.NONE and route_methods:
            methods |= set(route_methods)
    return sorted(methods)


async def _database_unavailable(_request: Request, exc: Exception) -> JSONResponse:
    # The database is down or every pooled connection is busy: a retry later can succeed, so 503, not 500.
    log.warning("database unavailable: %s", type(exc).__name__)
    detail = "the database is unavailable or saturated; retry later"
    return problem_response(503, DatabaseUnavailableError.title, detail, headers={"Retry-After": "5"})


def install_problem_handlers(app: FastAPI) -> None:
    app.add_exception_handler(HoiRefineError, _hoi_refine_error)
    app.add_exception_handler(RequestValidationError, _request_validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(sa_exc.OperationalError, _database_unavailable)
    app.add_exception_handler(sa_exc.TimeoutError, _database_unavailable)
    # Anything else is answered by ``service.middleware.CatchAll`` (a 500 with a correlation id that keeps
    # the connection open); an ``Exception`` handler here would be run by Starlette's ServerErrorMiddleware,
    # which re-raises after answering, and uvicorn then drops the keep-alive connection.
