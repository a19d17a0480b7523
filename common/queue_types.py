"""What ``common.queue.JobQueue`` hands out: plain, immutable records (no ORM objects escape the queue)."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from common.job_options import JobOptions
from common.job_state import ACTIVE, FINISHED, JobState


@dataclass(frozen=True)
class JobRecord:
    """One job as the API and the CLI see it."""

    id: str
    owner_key_id: str
    name: str
    state: JobState
    priority: int
    attempt: int
    max_attempts: int
    options: dict[str, Any]
    num_frames: int
    cancel_requested: bool
    progress: dict[str, Any] | None
    errors: list[dict[str, Any]]
    idempotency_key: str | None
    payload_hash: str
    worker_id: str | None
    lease_expires_at: datetime | None
    not_before: datetime | None
    created_at: datetime
    queued_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime
    #: The result's summary (metrics, config, versions) once SUCCEEDED; None before, or when not loaded.
    summary: dict[str, Any] | None = None
    batch_id: str | None = None
    #: ``executable`` / ``not_executable`` / ``unknown`` once SUCCEEDED (``common.batch_metrics.OUTCOMES``), with
    #: its short form (protocol, reasons, refined E_t / E_r); None before.
    outcome: str | None = None
    outcome_detail: dict[str, Any] | None = None
    #: The files stored beside the result (names, types, sizes; no data), once SUCCEEDED.
    files: tuple[Artifact, ...] = ()

    @property
    def is_terminal(self) -> bool:
        return self.state in FINISHED


@dataclass(frozen=True)
class Artifact:
    """A file stored beside a job's result (``common.db_models.JobArtifact``); ``data`` empty in listings."""

    name: str
    content_type: str
    data: bytes = b""
    size_bytes: int = 0


@dataclass(frozen=True)
class ClaimedJob:
    """What a worker gets from ``claim``: everything needed to run the job and to prove its lease."""

    job_id: str
    lease_token: str
    attempt: int
    payload: bytes
    options: JobOptions
    name: str
    lease_expires_at: datetime


@dataclass(frozen=True)
class JobEventRecord:
    id: int
    job_id: str
    at: datetime
    kind: str
    detail: dict[str, Any]


@dataclass(frozen=True)
class QueueStats:
    """Figures for ``/metrics``: jobs per state, claims so far, and recent durations in seconds."""

    jobs_by_state: dict[str, int]
    claims_total: int
    queue_wait_seconds: list[float]
    run_seconds: list[float]


@dataclass(frozen=True)
class BatchRecord:
    """A batch with its jobs counted per state; ``metrics`` (``common.batch_metrics``) only from ``get_batch``."""

    id: str
    owner_key_id: str
    name: str
    meta: dict[str, Any]
    created_at: datetime
    counts: dict[str, int]
    metrics: dict[str, Any] | None = None
    #: SUCCEEDED jobs per outcome (``executable``, ``not_executable``, ``unknown``).
    outcomes: dict[str, int] = field(default_factory=dict)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    @property
    def state(self) -> str:
        """EMPTY (no job yet), ACTIVE (a job is QUEUED or RUNNING) or COMPLETED (every job finished)."""
        if self.total == 0:
            return "EMPTY"
        return "ACTIVE" if any(self.counts.get(s, 0) for s in ACTIVE) else "COMPLETED"


@dataclass(frozen=True)
class WebhookRecord:
    id: str
    owner_key_id: str
    url: str
    event_types: list[str]
    created_at: datetime


@dataclass(frozen=True)
class DeliveryRecord:
    """One row of the delivery log (``payload`` is what is, or was, sent)."""

    id: int
    webhook_id: str
    msg_id: str
    event_type: str
    payload: dict[str, Any]
    state: str
    attempts: int
    next_attempt_at: datetime
    last_status: int | None
    last_error: str | None
    log: list[dict[str, Any]]
    created_at: datetime
    delivered_at: datetime | None


@dataclass(frozen=True)
class DeliveryToSend:
    """A due delivery claimed by the dispatcher: where to send it, with what secret, which attempt this is."""

    id: int
    url: str
    secret: str
    msg_id: str
    payload: dict[str, Any]
    attempt: int
