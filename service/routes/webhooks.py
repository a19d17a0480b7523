"""``/v1/webhooks``: signed notifications of job and batch state changes (issue #20 item 2).

Registered per API key; each sees only its own. The secret is returned once, at creation. Deliveries are
sent by the dispatcher (``service.webhook_dispatcher``), never by a worker, and logged per attempt.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Response

from service.deps import KeyDep, WebhooksDep, reject_unknown_query_parameters
from service.routes.jobs import COMMON_ERRORS, PROBLEM
from service.schemas_batches import (
    DeliveriesPublic,
    DeliveryPublic,
    WebhookCreate,
    WebhookCreated,
    WebhookPublic,
    WebhooksPublic,
)

router = APIRouter(
    prefix="/v1/webhooks",
    tags=["webhooks"],
    responses=COMMON_ERRORS,
    dependencies=[Depends(reject_unknown_query_parameters)],
)


@router.post("", status_code=201, response_model=WebhookCreated, responses={400: PROBLEM},
             summary="Register an endpoint; the answer holds its signing secret (shown only once)")  # fmt: skip
def create_webhook(body: WebhookCreate, response: Response, webhooks: WebhooksDep, key_id: KeyDep) -> WebhookCreated:
    hook, secret = webhooks.create_webhook(key_id, str(body.url), [str(t) for t in body.event_types])
    response.headers["Location"] = f"/v1/webhooks/{hook.id}"
    return WebhookCreated(**WebhookPublic.from_record(hook).model_dump(), secret=secret)


@router.get("", response_model=WebhooksPublic, summary="Your webhooks")
def list_webhooks(webhooks: WebhooksDep, key_id: KeyDep) -> WebhooksPublic:
    return WebhooksPublic(data=[WebhookPublic.from_record(h) for h in webhooks.list_webhooks(key_id)])


@router.delete("/{webhook_id}", status_code=204, summary="Remove a webhook and its delivery log")
def delete_webhook(webhook_id: str, webhooks: WebhooksDep, key_id: KeyDep) -> Response:
    webhooks.delete_webhook(key_id, webhook_id)
    return Response(status_code=204)


@router.get("/{webhook_id}/deliveries", response_model=DeliveriesPublic,
            summary="The delivery log, newest first: state, attempts, each attempt's status or error")  # fmt: skip
def list_deliveries(
    webhook_id: str,
    webhooks: WebhooksDep,
    key_id: KeyDep,
    limit: Annotated[int, Query(ge=1, le=500)] = 100,
    before_id: Annotated[int | None, Query(ge=1)] = None,
) -> DeliveriesPublic:
    rows = webhooks.webhook_deliveries(key_id, webhook_id, limit=limit, before_id=before_id)
    return DeliveriesPublic(
        webhook_id=webhook_id,
        data=[DeliveryPublic.from_record(d) for d in rows],
        next_before_id=rows[-1].id if len(rows) == limit else None,
    )
