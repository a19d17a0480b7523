"""Database models: jobs, their inputs and results, the append-only event log, API keys, batches and webhooks
(DESIGN §2, issue #20).

The schema changes only through an Alembic migration (``migrations/versions``); ``alembic check`` in
``tests/migration`` proves these models and the migrations agree. Queries live in ``common.queue`` (jobs)
and ``common.api_key_store`` (API keys) only; other modules read these classes for their column names,
never to write SQL.

Times are timezone-aware UTC in Python. SQLite has no time zone type, so ``UTCDateTime`` stores naive UTC
there and re-attaches UTC on the way out; comparisons in SQL stay correct because every value is UTC.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, ClassVar

import sqlalchemy as sa
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

from common.job_state import JobState

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class UTCDateTime(TypeDecorator[datetime]):
    """Aware UTC datetimes on every backend (naive UTC inside SQLite)."""

    impl = sa.DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("UTCDateTime needs an aware datetime")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def utcnow() -> datetime:
    return datetime.now(UTC)


class Base(DeclarativeBase):
    metadata = sa.MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map: ClassVar[dict[Any, Any]] = {datetime: UTCDateTime, dict[str, Any]: sa.JSON, list[Any]: sa.JSON}


class ApiKey(Base):
    """A client's bearer key; only its SHA-256 is stored (the plaintext is shown once at creation)."""

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(sa.String(32), primary_key=True)
    name: Mapped[str] = mapped_column(sa.String(200))
    key_hash: Mapped[str] = mapped_column(sa.String(64), unique=True)
    #: First characters of the key, so an operator can tell keys apart in ``keys list``.
    prefix: Mapped[str] = mapped_column(sa.String(16))
    created_at: Mapped[datetime]
    revoked_at: Mapped[datetime | None]


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = (
        sa.CheckConstraint(f"state IN ({', '.join(repr(s.value) for s in JobState)})", name="state"),
        sa.UniqueConstraint("owner_key_id", "idempotency_key", name="uq_jobs_owner_idempotency"),
        # claim: the oldest, highest-priority QUEUED job.
        sa.Index("ix_jobs_claim", "state", "priority", "created_at"),
        # listing: keyset pagination per owner, newest first.
        sa.Index("ix_jobs_owner_created", "owner_key_id", "created_at", "id"),
        sa.Index("ix_jobs_lease", "state", "lease_expires_at"),
        # a batch's counts, report and events.
        sa.Index("ix_jobs_batch", "batch_id", "state"),
        # listing by outcome: keyset pagination per owner within one outcome.
        sa.Index("ix_jobs_owner_outcome", "owner_key_id", "outcome", "created_at", "id"),
    )

    id: Mapped[str] = mapped_column(sa.String(32), primary_key=True)
    owner_key_id: Mapped[str] = mapped_column(sa.String(32), sa.ForeignKey("api_keys.id"))
    #: The batch the job was submitted into (same owner), or None.
    batch_id: Mapped[str | None] = mapped_column(sa.String(32), sa.ForeignKey("batches.id"))
    name: Mapped[str] = mapped_column(sa.String(200))
    #: A ``common.job_state.JobState`` value.
    state: Mapped[str] = mapped_column(sa.String(16))
    priority: Mapped[int] = mapped_column(sa.Integer, default=0)
    #: 1 on the first run; +1 each time an expired lease or a retryable failure requeues the job.
    attempt: Mapped[int] = mapped_column(sa.Integer, default=1)
    idempotency_key: Mapped[str | None] = mapped_column(sa.String(200))
    #: SHA-256 over the sequence bytes and the canonical options JSON (Idempotency-Key comparison).
    payload_hash: Mapped[str] = mapped_column(sa.String(64))
    options: Mapped[dict[str, Any]]
    num_frames: Mapped[int] = mapped_column(sa.Integer)
    cancel_requested: Mapped[bool] = mapped_column(sa.Boolean, default=False)
    worker_id: Mapped[str | None] = mapped_column(sa.String(200))
    lease_token: Mapped[str | None] = mapped_column(sa.String(32))
    lease_expires_at: Mapped[datetime | None]
    #: Requeue backoff: claim ignores the job before this time.
    not_before: Mapped[datetime | None]
    progress: Mapped[dict[str, Any] | None]
    #: Error history, one entry per failed attempt: {attempt, at, error}.
    errors: Mapped[list[Any]]
    created_at: Mapped[datetime]
    #: When the job last entered QUEUED (queue-wait metric).
    queued_at: Mapped[datetime]
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    updated_at: Mapped[datetime]
    #: Set with the result (``common.batch_metrics.outcome_columns``): ``executable`` / ``not_executable`` (the
    #: refined sequence passes the paper's protocol or not), ``unknown`` for a result that carries no outcome
    #: (made before outcomes existed); None until the job SUCCEEDED.
    outcome: Mapped[str | None] = mapped_column(sa.String(16))
    #: The outcome's short form for listings: protocol, reasons, refined E_t / E_r on that protocol.
    outcome_detail: Mapped[dict[str, Any] | None]


class JobInput(Base):
    """The submitted sequence as native NPZ bytes (already zlib-compressed by ``np.savez_compressed``)."""

    __tablename__ = "job_inputs"

    job_id: Mapped[str] = mapped_column(sa.String(32), sa.ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    payload: Mapped[bytes] = mapped_column(sa.LargeBinary)
    size_bytes: Mapped[int] = mapped_column(sa.Integer)


class JobResult(Base):
    """The result NPZ (compressed, ``common.result_format``) with its summary JSON beside it."""

    __tablename__ = "job_results"

    job_id: Mapped[str] = mapped_column(sa.String(32), sa.ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True)
    result: Mapped[bytes] = mapped_column(sa.LargeBinary)
    size_bytes: Mapped[int] = mapped_column(sa.Integer)
    summary: Mapped[dict[str, Any]]
    created_at: Mapped[datetime]


class JobArtifact(Base):
    """A file made beside a job's result (``name`` e.g. ``video.mp4``, ``plots/errors.png``): written with the
    result in the same transaction, deleted with the job."""

    __tablename__ = "job_artifacts"

    job_id: Mapped[str] = mapped_column(
        sa.String(32), sa.ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True
    )
    name: Mapped[str] = mapped_column(sa.String(100), primary_key=True)
    content_type: Mapped[str] = mapped_column(sa.String(100))
    data: Mapped[bytes] = mapped_column(sa.LargeBinary)
    size_bytes: Mapped[int] = mapped_column(sa.Integer)
    created_at: Mapped[datetime]


class JobEvent(Base):
    """Append-only log of state changes. No foreign key: a deleted job's history stays readable."""

    __tablename__ = "job_events"
    __table_args__ = (sa.Index("ix_job_events_job", "job_id", "id"),)

    id: Mapped[int] = mapped_column(sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True)
    job_id: Mapped[str] = mapped_column(sa.String(32))
    at: Mapped[datetime]
    kind: Mapped[str] = mapped_column(sa.String(32))
    detail: Mapped[dict[str, Any]]


class Batch(Base):
    """A named set of jobs of one key (a dataset submitted together); its counts and metrics are derived."""

    __tablename__ = "batches"
    __table_args__ = (sa.Index("ix_batches_owner_created", "owner_key_id", "created_at", "id"),)

    id: Mapped[str] = mapped_column(sa.String(32), primary_key=True)
    owner_key_id: Mapped[str] = mapped_column(sa.String(32), sa.ForeignKey("api_keys.id"))
    name: Mapped[str] = mapped_column(sa.String(200))
    meta: Mapped[dict[str, Any]]
    #: The batch state last announced to webhooks (ACTIVE / COMPLETED), so each change is sent once.
    notified_state: Mapped[str | None] = mapped_column(sa.String(16))
    created_at: Mapped[datetime]


class Webhook(Base):
    """An endpoint of one key that receives signed job and batch state changes (Standard Webhooks)."""

    __tablename__ = "webhooks"
    __table_args__ = (sa.Index("ix_webhooks_owner", "owner_key_id", "created_at"),)

    id: Mapped[str] = mapped_column(sa.String(32), primary_key=True)
    owner_key_id: Mapped[str] = mapped_column(sa.String(32), sa.ForeignKey("api_keys.id"))
    url: Mapped[str] = mapped_column(sa.String(2000))
    #: ``whsec_<base64>``: needed in clear to sign; shown to the client once, at creation.
    secret: Mapped[str] = mapped_column(sa.String(100))
    #: Event types sent (``job.succeeded``, ``batch.completed``...); empty = all.
    event_types: Mapped[list[Any]]
    created_at: Mapped[datetime]


class WebhookDelivery(Base):
    """The outbox and the delivery log: one row per (webhook, event), retried with backoff until delivered."""

    __tablename__ = "webhook_deliveries"
    __table_args__ = (
        sa.Index("ix_webhook_deliveries_due", "state", "next_attempt_at"),
        sa.Index("ix_webhook_deliveries_webhook", "webhook_id", "id"),
    )

    id: Mapped[int] = mapped_column(sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True)
    webhook_id: Mapped[str] = mapped_column(sa.String(32), sa.ForeignKey("webhooks.id", ondelete="CASCADE"))
    #: ``webhook-id`` header: the same on every retry so receivers can drop duplicates.
    msg_id: Mapped[str] = mapped_column(sa.String(40))
    event_type: Mapped[str] = mapped_column(sa.String(40))
    payload: Mapped[dict[str, Any]]
    #: PENDING (due at ``next_attempt_at``), DELIVERED, or FAILED (attempts used up).
    state: Mapped[str] = mapped_column(sa.String(16))
    attempts: Mapped[int] = mapped_column(sa.Integer, default=0)
    next_attempt_at: Mapped[datetime]
    last_status: Mapped[int | None] = mapped_column(sa.Integer)
    last_error: Mapped[str | None] = mapped_column(sa.String(500))
    #: One entry per attempt: {at, status, error, ms}.
    log: Mapped[list[Any]]
    created_at: Mapped[datetime]
    delivered_at: Mapped[datetime | None]


class EventCursor(Base):
    """How far a consumer of ``job_events`` has read (the webhook fan-out), so each event is handled once."""

    __tablename__ = "event_cursors"

    name: Mapped[str] = mapped_column(sa.String(40), primary_key=True)
    last_event_id: Mapped[int] = mapped_column(sa.BigInteger)
