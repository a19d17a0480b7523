"""Request and response bodies of ``/v1/batches`` and ``/v1/webhooks`` (issue #20)."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import AnyHttpUrl, BaseModel, ConfigDict, Field

from common.queue_types import BatchRecord, DeliveryRecord, WebhookRecord
from common.webhook_store import ALL_EVENT_TYPES
from service.links import batch_links
from service.schemas import LinkPublic

BatchState = Literal["EMPTY", "ACTIVE", "COMPLETED"]
WebhookEventType = Literal[ALL_EVENT_TYPES]  # type: ignore[valid-type]


class BatchCreate(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    name: str = Field(default="batch", min_length=1, max_length=200)
    meta: dict[str, str] = Field(default_factory=dict, description="Free labels (dataset, split, ...)")


class StageMetrics(BaseModel):
    """Means over the batch's SUCCEEDED sequences that carry each metric (null when none does)."""

    n: int = Field(description="sequences with this protocol and stage")
    SR: float | None = Field(description="success rate: share of sequences within 3 cm / 30 deg on every frame")
    E_t: float | None = Field(description="mean object position error, cm")
    E_r: float | None = Field(description="mean object rotation error, deg")
    E_j: float | None = Field(description="mean hand joint error, cm")
    E_ft: float | None = Field(description="mean fingertip error, cm")
    penetration_mean_mm: float | None = Field(
        default=None, description="mean over sequences of the mean per-frame deepest hand-object penetration, mm"
    )
    penetration_max_mm: float | None = Field(
        default=None, description="mean over sequences of the deepest hand-object penetration, mm"
    )


class BatchPublic(BaseModel):
    id: str
    name: str
    meta: dict[str, Any]
    created_at: datetime
    state: BatchState = Field(description="EMPTY (no job), ACTIVE (a job is QUEUED or RUNNING), COMPLETED")
    total: int
    outcomes: dict[str, int] = Field(
        default_factory=dict, description="SUCCEEDED jobs per outcome: executable, not_executable, unknown"
    )
    counts: dict[str, int] = Field(description="jobs per state")
    metrics: dict[str, dict[str, StageMetrics]] | None = Field(
        default=None,
        description="protocol (all_frames; paper: frames 10 onward) -> raw | refined -> means over the SUCCEEDED "
        "jobs; only on GET /v1/batches/{id}",
    )
    links: dict[str, LinkPublic] = Field(
        default_factory=dict,
        description="self, jobs, not_executable and failed jobs, events, report_csv, report_parquet, dashboard",
    )

    @classmethod
    def from_record(cls, batch: BatchRecord) -> BatchPublic:
        return cls(
            id=batch.id, name=batch.name, meta=batch.meta, created_at=batch.created_at, state=batch.state,
            total=batch.total, outcomes=batch.outcomes, counts=batch.counts, metrics=batch.metrics,
            links=batch_links(batch.id),
        )  # fmt: skip


class BatchesPublic(BaseModel):
    data: list[BatchPublic]
    count: int
    next_page_token: str | None = Field(
        description="Opaque token issued by the service: pass it as page_token for the next page; null on the last page"
    )


class BatchActionPublic(BaseModel):
    batch: BatchPublic
    changed: int = Field(description="jobs cancelled / flagged for cancellation, or requeued")


class WebhookCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    url: AnyHttpUrl = Field(
        description="http:// or https:// URL whose host is a public address: a host that is, or resolves to, a "
        "loopback, private, link-local, multicast, unspecified or reserved address (IPv4 or IPv6) is refused "
        "with 422 unless the operator allows it (HOI_REFINE_WEBHOOK_ALLOW_TARGETS); checked again at each "
        "delivery, which never follows redirects"
    )
    event_types: list[WebhookEventType] = Field(
        default_factory=list, description="Event types to send; empty = all"
    )


class WebhookPublic(BaseModel):
    id: str
    url: str
    event_types: list[str]
    created_at: datetime

    @classmethod
    def from_record(cls, hook: WebhookRecord) -> WebhookPublic:
        return cls(id=hook.id, url=hook.url, event_types=hook.event_types, created_at=hook.created_at)


class WebhookCreated(WebhookPublic):
    secret: str = Field(description="whsec_...: verifies the webhook-signature header; shown only now")


class WebhooksPublic(BaseModel):
    data: list[WebhookPublic]


class DeliveryPublic(BaseModel):
    id: int
    msg_id: str = Field(description="the webhook-id header (the same on every retry)")
    event_type: str
    state: Literal["PENDING", "DELIVERED", "FAILED"]
    attempts: int
    next_attempt_at: datetime
    last_status: int | None
    last_error: str | None
    log: list[dict[str, Any]] = Field(description="one entry per attempt: at, attempt, status, error, ms")
    payload: dict[str, Any]
    created_at: datetime
    delivered_at: datetime | None

    @classmethod
    def from_record(cls, d: DeliveryRecord) -> DeliveryPublic:
        return cls(
            id=d.id, msg_id=d.msg_id, event_type=d.event_type, state=d.state, attempts=d.attempts,
            next_attempt_at=d.next_attempt_at, last_status=d.last_status, last_error=d.last_error, log=d.log,
            payload=d.payload, created_at=d.created_at, delivered_at=d.delivered_at,
        )  # fmt: skip


class DeliveriesPublic(BaseModel):
    webhook_id: str
    data: list[DeliveryPublic]
    next_before_id: int | None = Field(description="pass as before_id for older deliveries; null at the end")
