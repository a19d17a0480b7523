"""Operations endpoints: liveness, readiness (database reachable and migrated to head), Prometheus."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST

from common.database import database_ready
from service.deps import KeyDep
from service.metrics import render
from service.problems import problem_response

router = APIRouter(tags=["operations"])


@router.get("/healthz", summary="The process is up")
def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.get("/readyz", summary="The database answers and its schema is at the migration head",
            responses={503: {"content": {"application/problem+json": {}}}})  # fmt: skip
def readyz(request: Request) -> Response:
    ready, reason = database_ready(request.app.state.engine)
    if not ready:
        return problem_response(503, "Not ready", reason)
    return Response('{"status":"ready"}', media_type="application/json")


@router.get("/metrics", summary="Prometheus metrics (needs an API key: deployment-wide job totals)",
            response_class=Response, responses={200: {"content": {CONTENT_TYPE_LATEST: {}}},
                                                401: {"content": {"application/problem+json": {}}}})  # fmt: skip
def metrics(request: Request, _key: KeyDep) -> Response:
    # Protected rather than public (issue #16): the totals say how busy the deployment is and when its
    # clients work, which is nobody's business without a key. Any valid key may scrape (Prometheus:
    # ``authorization: {credentials: KEY}``); no job ids, names or key ids are in it.
    return Response(render(request.app.state.metrics_registry), media_type=CONTENT_TYPE_LATEST)
