"""The job queue: the one class that owns every queue query (DESIGN §2, §4; like procrastinate's ``JobManager``).

Guarantees: a job is RUNNING under exactly one lease token at a time; every worker write (heartbeat,
complete, fail, acknowledge_cancel, release) names its token and changes nothing when the token no longer
holds the job (``LeaseLostError``), so a worker whose lease expired cannot overwrite the requeued run:
at-least-once execution, exactly-once effect on the result. Every state change appends a ``job_events`` row
in the same transaction.

Claiming: PostgreSQL picks the row with ``FOR UPDATE SKIP LOCKED`` (concurrent claimers skip each other's
rows instead of queueing on them); SQLite runs the same ``UPDATE ... WHERE id = (SELECT ...) RETURNING`` in a
``BEGIN IMMEDIATE`` transaction, which takes the database write lock up front so two claimers cannot both
read the same QUEUED row. Order: priority (high first), then age.

API keys have their own small store, ``common.api_key_store.ApiKeyStore``; job states are
``common.job_state.JobState``.
"""

from __future__ import annotations

import builtins
import dataclasses
import hashlib
import json
import re
import secrets
import uuid
from collections.abc import Callable, Sequence
from datetime import UTC, datetime, timedelta
from typing import Any, cast

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine, Row

from common.batch_metrics import OUTCOMES, aggregate, outcome_columns
from common.database import Transactions
from common.db_models import Batch, Job, JobArtifact, JobEvent, JobInput, JobResult, utcnow
from common.errors import (
    ConflictError,
    FieldProblem,
    IdempotencyMismatchError,
    InvalidRequestError,
    LeaseLostError,
    LimitExceededError,
    NotFoundError,
)
from common.job_options import JobOptions
from common.job_state import ACTIVE, JobState
from common.progress import finished_progress
from common.queue_types import Artifact, BatchRecord, ClaimedJob, JobEventRecord, JobRecord, QueueStats
from common.safe_text import shown
from common.settings import Settings, get_settings

# Core tables of the mapped models: the queue speaks SQL expressions, never ORM sessions.
jobs = cast(sa.Table, Job.__table__)
inputs = cast(sa.Table, JobInput.__table__)
results = cast(sa.Table, JobResult.__table__)
events = cast(sa.Table, JobEvent.__table__)
artifacts = cast(sa.Table, JobArtifact.__table__)
batches = cast(sa.Table, Batch.__table__)

MAX_PAGE_SIZE = 500
#: Events one stream read returns at most (the stream asks again at once while a read comes back full).
EVENTS_PER_READ = 200
#: How old an event must be before a stream over several jobs (or the webhook fan-out) passes it on
#: PostgreSQL: by then every transaction that took a smaller id has committed.
EVENT_LAG = timedelta(seconds=2)
_VERSION_SQL = sa.text("SELECT owner_key_id, updated_at FROM jobs WHERE id = :job_id")


def payload_hash(payload: bytes, options: JobOptions) -> str:
    """SHA-256 over the sequence bytes and the options set apart from their defaults (what an Idempotency-Key
    must match): an option added by a later release, at its default, leaves it unchanged."""
    return _hash(payload, options.model_dump(mode="json", exclude_defaults=True))


def legacy_payload_hash(payload: bytes, options: JobOptions) -> str:
    """The hash jobs stored before it left defaults out (every option spelled out)."""
    return _hash(payload, options.model_dump(mode="json"))


def _hash(payload: bytes, options: dict[str, Any]) -> str:
    options_json = json.dumps(options, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(payload + b"\x00" + options_json.encode()).hexdigest()


class JobQueue:
    """Submit, claim, heartbeat, complete, fail, cancel, retry, requeue, delete; owner-scoped reads and counts;
    batches and the event reads behind the event streams.

    Sections: construction and transactions, submission, owner-scoped reads, counts, the worker side,
    owner-scoped actions, batches, event reads, row helpers. API keys live in
    ``common.api_key_store.ApiKeyStore``, webhooks (an outbox fed from ``job_events``) in
    ``common.webhook_store.WebhookStore``.
    """

    def __init__(self, engine: Engine, settings: Settings | None = None) -> None:
        self.engine = engine
        self.settings = settings if settings is not None else get_settings()
        self.tx = Transactions(engine)

    @staticmethod
    def _event(conn: Connection, job_id: str, kind: str, now: datetime, **detail: Any) -> None:
        conn.execute(sa.insert(events).values(job_id=job_id, at=now, kind=kind, detail=detail))

    # ------------------------------------------------------------------ submission
    def submit(
        self,
        owner_key_id: str,
        payload: bytes,
        options: JobOptions,
        idempotency_key: str | None,
        name: str,
        num_frames: int,
        batch_id: str | None = None,
    ) -> tuple[JobRecord, bool]:
        """Queue a job, into ``batch_id`` when given (a batch of the same key); returns (job, created).
        Same Idempotency-Key + same payload -> the first job (adopted into ``batch_id`` if it had no batch)."""
        digest = payload_hash(payload, options)
        try:
            with self.tx.write() as conn:
                if self.tx.postgres:
                    # Serialise one owner's submissions: the idempotency lookup and the active-jobs limit
                    # below then see every committed sibling (SQLite's BEGIN IMMEDIATE already does this).
                    conn.execute(sa.select(sa.func.pg_advisory_xact_lock(sa.func.hashtext(owner_key_id))))
                if batch_id is not None:
                    self._owned_batch(conn, owner_key_id, batch_id)
                if idempotency_key is not None:
                    existing = self._by_idempotency_key(conn, owner_key_id, idempotency_key)
                    if existing is not None:
                        match = self._idempotent_match(existing, digest, payload, options)
                        return self._into_batch(conn, match, batch_id), False
                active = self._count_active(conn, owner_key_id)
                if active >= self.settings.max_active_jobs_per_key:
                    raise LimitExceededError(
                        f"this API key already has {active} active jobs (limit "
                        f"{self.settings.max_active_jobs_per_key}); wait for some to finish",
                        retry_after=self.settings.active_jobs_retry_after_seconds,
                    )
                now = utcnow()
                job_id = uuid.uuid4().hex
                conn.execute(
                    sa.insert(jobs).values(
                        id=job_id, owner_key_id=owner_key_id, batch_id=batch_id, name=name[:200],
                        state=JobState.QUEUED,
                        priority=options.priority, attempt=1, idempotency_key=idempotency_key,
                        payload_hash=digest, options=options.model_dump(mode="json"), num_frames=num_frames,
                        cancel_requested=False, errors=[], created_at=now, queued_at=now, updated_at=now,
                    )
                )  # fmt: skip
                conn.execute(sa.insert(inputs).values(job_id=job_id, payload=payload, size_bytes=len(payload)))
                self._event(conn, job_id, "submitted", now, priority=options.priority, num_frames=num_frames)
                record = self._get(conn, job_id, None)
            return record, True
        except sa.exc.IntegrityError:
            # A concurrent submission with the same key won the unique constraint; answer with its job.
            if idempotency_key is None:
                raise
            with self.tx.read() as conn:
                existing = self._by_idempotency_key(conn, owner_key_id, idempotency_key)
            if existing is None:
                raise
            if existing.batch_id != batch_id:
                raise
            return self._idempotent_match(existing, digest, payload, options), False

    def _into_batch(self, conn: Connection, job: JobRecord, batch_id: str | None) -> JobRecord:
        """A job found by its Idempotency-Key, re-sent with ``batch_id``: adopt it when it has no batch yet
        (a manifest written before batches existed), refuse when it belongs to another batch."""
        if batch_id is None or job.batch_id == batch_id:
            return job
        if job.batch_id is not None:
            raise ConflictError(f"Idempotency-Key names job {job.id}, which is in batch {job.batch_id}, not {batch_id}")
        now = utcnow()
        conn.execute(sa.update(jobs).where(jobs.c.id == job.id).values(batch_id=batch_id, updated_at=now))
        self._event(conn, job.id, "batched", now, batch_id=batch_id)
        return self._get(conn, job.id, None)

    def _by_idempotency_key(self, conn: Connection, owner_key_id: str, key: str) -> JobRecord | None:
        row = conn.execute(
            self._job_select().where(jobs.c.owner_key_id == owner_key_id, jobs.c.idempotency_key == key)
        ).first()
        return None if row is None else self._record(row)

    @staticmethod
    def _idempotent_match(existing: JobRecord, digest: str, payload: bytes, options: JobOptions) -> JobRecord:
        if existing.payload_hash != digest and existing.payload_hash != legacy_payload_hash(payload, options):
            raise IdempotencyMismatchError(
                f"Idempotency-Key was already used for job {existing.id} with a different sequence or options"
            )
        return existing

    # ------------------------------------------------------------------ owner-scoped reads
    def get(self, owner_key_id: str | None, job_id: str) -> JobRecord:
        """The job with its summary; ``NotFoundError`` when missing or owned by another key (None = any)."""
        with self.tx.read() as conn:
            return self._get(conn, job_id, owner_key_id)

    def version(self, owner_key_id: str | None, job_id: str) -> str:
        """An opaque version of the job: its ``updated_at`` as the driver returns it. Every write to a job sets
        ``updated_at``, so this versions the whole representation (the status poll's ETag and cache key).
        ``NotFoundError`` as ``get``.

        The status poll's hot path: one indexed single-row SELECT in autocommit (no BEGIN / ROLLBACK round
        trips), as plain SQL (no type processing: the value is only compared, never interpreted)."""
        _require_plain_id(job_id)
        with self.engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
            row = conn.execute(_VERSION_SQL, {"job_id": job_id}).first()
        if row is None or (owner_key_id is not None and row[0] != owner_key_id):
            raise NotFoundError(f"no job {job_id}")
        return str(row[1])

    def list(
        self,
        owner_key_id: str | None,
        state: str | None = None,
        page_size: int = 50,
        page_token: str | None = None,
        batch_id: str | None = None,
        outcome: str | None = None,
    ) -> tuple[builtins.list[JobRecord], str | None]:
        """Newest first, keyset-paginated on (created_at, id); returns (jobs, next_page_token). ``outcome``
        (``common.batch_metrics.OUTCOMES``) keeps SUCCEEDED jobs of that outcome only."""
        page_size = max(1, min(page_size, MAX_PAGE_SIZE))
        query = self._job_select(with_summary=False)
        if owner_key_id is not None:
            query = query.where(jobs.c.owner_key_id == owner_key_id)
        if state is not None:
            query = query.where(jobs.c.state == state)
        if batch_id is not None:
            query = query.where(jobs.c.batch_id == batch_id)
        if outcome is not None:
            query = query.where(jobs.c.outcome == _known_outcome(outcome))
        if page_token is not None:
            created, last_id = _decode_page_token(page_token)
            query = query.where(
                sa.or_(jobs.c.created_at < created, sa.and_(jobs.c.created_at == created, jobs.c.id < last_id))
            )
        if batch_id is not None and not _PLAIN_ID.fullmatch(batch_id):
            return [], None  # no batch has such an id (and PostgreSQL cannot even compare a NUL)
        query = query.order_by(jobs.c.created_at.desc(), jobs.c.id.desc()).limit(page_size + 1)
        with self.tx.read() as conn:
            page = [self._record(r) for r in conn.execute(query)]
            more = len(page) > page_size
            page = self._with_files(conn, page[:page_size])
        return page, (_encode_page_token(page[-1].created_at, page[-1].id) if more else None)

    def get_result(self, owner_key_id: str | None, job_id: str) -> tuple[bytes, dict[str, Any]]:
        """(result NPZ bytes, summary) of a SUCCEEDED job; ``ConflictError`` before that."""
        with self.tx.read() as conn:
            job = self._get(conn, job_id, owner_key_id)
            row = conn.execute(sa.select(results.c.result, results.c.summary).where(results.c.job_id == job_id)).first()
        if job.state != JobState.SUCCEEDED or row is None:
            raise ConflictError(f"job {job_id} is {job.state}; a result exists only once it has SUCCEEDED")
        return bytes(row.result), dict(row.summary)

    def list_artifacts(self, owner_key_id: str | None, job_id: str) -> builtins.list[Artifact]:
        """Names, types and sizes (no data) of a job's artifacts, by name; empty before it SUCCEEDED."""
        with self.tx.read() as conn:
            self._get(conn, job_id, owner_key_id)
            rows = conn.execute(
                sa.select(artifacts.c.name, artifacts.c.content_type, artifacts.c.size_bytes)
                .where(artifacts.c.job_id == job_id)
                .order_by(artifacts.c.name)
            ).all()
        return [Artifact(r.name, r.content_type, b"", r.size_bytes) for r in rows]

    def get_artifact(self, owner_key_id: str | None, job_id: str, name: str) -> Artifact:
        """One artifact with its data; ``ConflictError`` before the job SUCCEEDED, ``NotFoundError`` when the
        job has no such artifact (e.g. it ran with ``preview_video`` off)."""
        with self.tx.read() as conn:
            job = self._get(conn, job_id, owner_key_id)
            row = conn.execute(
                sa.select(artifacts.c.content_type, artifacts.c.data, artifacts.c.size_bytes).where(
                    artifacts.c.job_id == job_id, artifacts.c.name == name
                )
            ).first()
        if job.state != JobState.SUCCEEDED:
            raise ConflictError(f"job {job_id} is {job.state}; its files exist only once it has SUCCEEDED")
        if row is None:
            raise NotFoundError(f"job {job_id} has no {name!r} (the preview may have been skipped or failed)")
        return Artifact(name, row.content_type, bytes(row.data), row.size_bytes)

    def get_payload(self, job_id: str) -> bytes:
        _require_plain_id(job_id)
        with self.tx.read() as conn:
            blob = conn.execute(sa.select(inputs.c.payload).where(inputs.c.job_id == job_id)).scalar()
        if blob is None:
            raise NotFoundError(f"job {job_id} has no stored input")
        return bytes(blob)

    def events(self, owner_key_id: str | None, job_id: str) -> builtins.list[JobEventRecord]:
        _require_plain_id(job_id)
        with self.tx.read() as conn:
            if owner_key_id is not None:
                self._get(conn, job_id, owner_key_id)
            rows = conn.execute(sa.select(events).where(events.c.job_id == job_id).order_by(events.c.id)).all()
        return [_event_record(r) for r in rows]

    # ------------------------------------------------------------------ counts
    def count_active(self, owner_key_id: str) -> int:
        """Jobs of this key that are QUEUED or RUNNING (what ``max_active_jobs_per_key`` limits)."""
        with self.tx.read() as conn:
            return self._count_active(conn, owner_key_id)

    @staticmethod
    def _count_active(conn: Connection, owner_key_id: str) -> int:
        query = sa.select(sa.func.count()).select_from(jobs)
        query = query.where(jobs.c.owner_key_id == owner_key_id, jobs.c.state.in_(ACTIVE))
        return int(conn.execute(query).scalar_one())

    def stats(self, recent: int = 1000) -> QueueStats:
        """Jobs per state, claims so far, and queue-wait / run seconds of the ``recent`` latest started jobs."""
        with self.tx.read() as conn:
            per_state = conn.execute(sa.select(jobs.c.state, sa.func.count()).group_by(jobs.c.state)).all()
            claims = conn.execute(sa.select(sa.func.count()).where(events.c.kind == "claimed")).scalar_one()
            rows = conn.execute(
                sa.select(jobs.c.queued_at, jobs.c.started_at, jobs.c.finished_at)
                .where(jobs.c.started_at.is_not(None))
                .order_by(jobs.c.started_at.desc())
                .limit(recent)
            ).all()
        waits = [(r.started_at - r.queued_at).total_seconds() for r in rows if r.started_at >= r.queued_at]
        runs = [(r.finished_at - r.started_at).total_seconds() for r in rows if r.finished_at is not None]
        return QueueStats({str(k): int(v) for k, v in per_state}, int(claims), waits, runs)

    # ------------------------------------------------------------------ worker side
    def claim(
        self, worker_id: str, lease_seconds: float | None = None, now: datetime | None = None
    ) -> ClaimedJob | None:
        """Take the next runnable job (highest priority, oldest first) under a fresh lease, or None."""
        now = now or utcnow()
        lease = timedelta(seconds=lease_seconds if lease_seconds is not None else self.settings.lease_seconds)
        token = secrets.token_hex(16)
        pick = self.tx.locked(
            sa.select(jobs.c.id)
            .where(jobs.c.state == JobState.QUEUED, sa.or_(jobs.c.not_before.is_(None), jobs.c.not_before <= now))
            .order_by(jobs.c.priority.desc(), jobs.c.created_at, jobs.c.id)
            .limit(1),
            skip_locked=True,
        )
        with self.tx.write() as conn:
            row = conn.execute(
                sa.update(jobs)
                .where(jobs.c.id == pick.scalar_subquery(), jobs.c.state == JobState.QUEUED)
                .values(
                    state=JobState.RUNNING, lease_token=token, lease_expires_at=now + lease, worker_id=worker_id,
                    started_at=now, updated_at=now, progress=None,
                )
                .returning(jobs.c.id, jobs.c.attempt, jobs.c.options, jobs.c.name, jobs.c.queued_at)
            ).first()
            if row is None:
                return None
            payload = conn.execute(sa.select(inputs.c.payload).where(inputs.c.job_id == row.id)).scalar_one()
            wait_s = (now - row.queued_at).total_seconds()
            self._event(conn, row.id, "claimed", now, worker_id=worker_id, attempt=row.attempt, wait_s=wait_s)
        return ClaimedJob(
            job_id=row.id, lease_token=token, attempt=row.attempt, payload=bytes(payload),
            options=JobOptions.model_validate(row.options), name=row.name, lease_expires_at=now + lease,
        )  # fmt: skip

    def heartbeat(
        self, job_id: str, lease_token: str, progress: dict[str, Any] | None = None, lease_seconds: float | None = None
    ) -> bool:
        """Renew the lease and store progress; returns the cancel flag. ``LeaseLostError`` if the token lost it."""
        now = utcnow()
        lease = timedelta(seconds=lease_seconds if lease_seconds is not None else self.settings.lease_seconds)
        values: dict[str, Any] = {"lease_expires_at": now + lease, "updated_at": now}
        if progress is not None:
            values["progress"] = progress
        held = (jobs.c.id == job_id, jobs.c.lease_token == lease_token, jobs.c.state == JobState.RUNNING)
        with self.tx.write() as conn:
            before = None
            if progress is not None:
                before = conn.execute(self.tx.locked(sa.select(jobs.c.progress).where(*held))).first()
            update = sa.update(jobs).where(*held).values(**values)
            flag = conn.execute(update.returning(jobs.c.cancel_requested)).scalar()
            if flag is not None and before is not None and before.progress != progress:
                # Progress that moved is an event too (the event streams send it with an id, so a client
                # resumes after it); an unchanged renewal writes none, which bounds the log's growth.
                self._event(conn, job_id, "progress", now, progress=progress)
        if flag is None:
            raise LeaseLostError(f"job {job_id}: lease token no longer holds the job")
        return bool(flag)

    def _lease_row(self, conn: Connection, job_id: str, lease_token: str) -> Row[Any]:
        row = conn.execute(
            self.tx.locked(
                sa.select(
                    jobs.c.attempt, jobs.c.errors, jobs.c.cancel_requested, jobs.c.worker_id, jobs.c.progress
                ).where(jobs.c.id == job_id, jobs.c.lease_token == lease_token, jobs.c.state == JobState.RUNNING)
            )
        ).first()
        if row is None:
            raise LeaseLostError(f"job {job_id}: lease token no longer holds the job")
        return row

    def _settle(self, conn: Connection, job_id: str, lease_token: str, **values: Any) -> None:
        """End a lease: the row was locked by ``_lease_row`` in this transaction."""
        conn.execute(
            sa.update(jobs)
            .where(jobs.c.id == job_id, jobs.c.lease_token == lease_token)
            .values(lease_token=None, lease_expires_at=None, updated_at=values.pop("now"), **values)
        )

    def complete(
        self, job_id: str, lease_token: str, result: bytes, summary: dict[str, Any],
        artifacts: Sequence[Artifact] = (),
    ) -> None:
        """Store the result (and its artifacts: preview video, plots, ...) and mark SUCCEEDED, all in one
        token-checked transaction."""
        now = utcnow()
        with self.tx.write() as conn:
            row = self._lease_row(conn, job_id, lease_token)
            conn.execute(sa.delete(results).where(results.c.job_id == job_id))
            conn.execute(
                sa.insert(results).values(
                    job_id=job_id, result=result, size_bytes=len(result), summary=summary, created_at=now
                )
            )
            self._store_artifacts(conn, job_id, artifacts, now)
            outcome, detail = outcome_columns(summary)
            # A finished job shows "done", not its last window and ETA (``common.progress``).
            self._settle(conn, job_id, lease_token, now=now, state=JobState.SUCCEEDED, finished_at=now,
                         progress=finished_progress(row.progress), outcome=outcome, outcome_detail=detail)  # fmt: skip
            self._event(conn, job_id, "succeeded", now, result_bytes=len(result), outcome=outcome)

    @staticmethod
    def _store_artifacts(conn: Connection, job_id: str, items: Sequence[Artifact], now: datetime) -> None:
        names = [a.name for a in items]
        if len(set(names)) != len(names):
            raise ValueError(f"artifact names must be unique, got {names}")
        conn.execute(sa.delete(artifacts).where(artifacts.c.job_id == job_id))
        for a in items:
            conn.execute(
                sa.insert(artifacts).values(
                    job_id=job_id, name=a.name, content_type=a.content_type, data=a.data, size_bytes=len(a.data),
                    created_at=now,
                )
            )  # fmt: skip

    def fail(self, job_id: str, lease_token: str, error: str, retryable: bool = False) -> None:
        """Record an error; retryable errors requeue with backoff until ``max_attempts``, then FAILED."""
        now = utcnow()
        with self.tx.write() as conn:
            row = self._lease_row(conn, job_id, lease_token)
            self._after_attempt(conn, job_id, lease_token, row, error, retryable, now)

    def _after_attempt(
        self, conn: Connection, job_id: str, token: str, row: Row[Any], error: str, retryable: bool, now: datetime
    ) -> JobState:
        """Requeue (attempt + 1, backoff), cancel or fail a job whose attempt ended in ``error``."""
        errors = [*row.errors, {"attempt": row.attempt, "at": now.isoformat(), "error": error, "worker": row.worker_id}]
        if row.cancel_requested:
            state, extra = JobState.CANCELLED, {"finished_at": now}
        elif retryable and row.attempt < self.settings.max_attempts:
            # DESIGN §2 backoff: retry_backoff_seconds * 2**(attempt-1) before the next claim.
            delay = self.settings.retry_backoff_seconds * 2 ** (row.attempt - 1)
            state = JobState.QUEUED
            extra = {"attempt": row.attempt + 1, "not_before": now + timedelta(seconds=delay), "queued_at": now}
        else:
            state, extra = JobState.FAILED, {"finished_at": now}
        self._settle(conn, job_id, token, now=now, state=state, errors=errors, **extra)
        kind = {JobState.QUEUED: "requeued", JobState.FAILED: "failed", JobState.CANCELLED: "cancelled"}[state]
        self._event(conn, job_id, kind, now, attempt=row.attempt, error=error)
        return state

    def acknowledge_cancel(self, job_id: str, lease_token: str) -> None:
        """The worker saw the cancel flag and stopped: RUNNING -> CANCELLED."""
        now = utcnow()
        with self.tx.write() as conn:
            row = self._lease_row(conn, job_id, lease_token)
            if not row.cancel_requested:
                raise ConflictError(f"job {job_id}: cancellation was not requested")
            self._settle(conn, job_id, lease_token, now=now, state=JobState.CANCELLED, finished_at=now)
            self._event(conn, job_id, "cancelled", now, attempt=row.attempt)

    def release(self, job_id: str, lease_token: str) -> None:
        """Graceful shutdown: give the job back (QUEUED, same attempt), or CANCELLED if that was asked."""
        now = utcnow()
        with self.tx.write() as conn:
            row = self._lease_row(conn, job_id, lease_token)
            if row.cancel_requested:
                self._settle(conn, job_id, lease_token, now=now, state=JobState.CANCELLED, finished_at=now)
                self._event(conn, job_id, "cancelled", now, attempt=row.attempt)
            else:
                self._settle(conn, job_id, lease_token, now=now, state=JobState.QUEUED, not_before=None, queued_at=now)
                self._event(conn, job_id, "released", now, attempt=row.attempt, worker_id=row.worker_id)

    def requeue_expired(self, now: datetime | None = None) -> int:
        """Requeue RUNNING jobs whose lease ran out (attempt + 1, backoff); FAILED after max attempts."""
        now = now or utcnow()
        return self._requeue_running(
            jobs.c.lease_expires_at < now,
            lambda row: f"lease expired (worker {row.worker_id} stopped heartbeating)",
            now,
        )

    def requeue_worker_jobs(self, worker_id_prefix: str, reason: str, now: datetime | None = None) -> int:
        """Requeue (attempt + 1, as for an expired lease) the RUNNING jobs of workers whose id starts with
        ``worker_id_prefix``: a deployment found dead (``hoi-refine up`` after a SIGKILL) need not wait for
        their leases to run out."""
        return self._requeue_running(
            jobs.c.worker_id.startswith(worker_id_prefix, autoescape=True), lambda _row: reason, now or utcnow()
        )

    def _requeue_running(self, which: Any, reason: Callable[[Row[Any]], str], now: datetime) -> int:
        """The RUNNING jobs ``which`` selects end their attempt as lost (``_after_attempt``, retryable)."""
        with self.tx.write() as conn:
            rows = conn.execute(
                self.tx.locked(
                    sa.select(
                        jobs.c.id, jobs.c.lease_token, jobs.c.attempt, jobs.c.errors, jobs.c.cancel_requested,
                        jobs.c.worker_id,
                    ).where(jobs.c.state == JobState.RUNNING, which),
                    skip_locked=True,
                )
            ).all()  # fmt: skip
            for row in rows:
                self._after_attempt(conn, row.id, row.lease_token, row, reason(row), True, now)
        return len(rows)

    def cancel_jobs_of_key(self, key_id: str) -> tuple[int, int]:
        """Cancel every QUEUED job of an API key and flag its RUNNING ones (``keys revoke --cancel-jobs``):
        a revoked key can no longer see or cancel them itself. Returns (cancelled, flagged)."""
        now = utcnow()
        with self.tx.write() as conn:
            rows = conn.execute(
                self.tx.locked(
                    sa.select(jobs.c.id, jobs.c.state).where(
                        jobs.c.owner_key_id == key_id, jobs.c.state.in_(ACTIVE)
                    )
                )
            ).all()
            queued = [r.id for r in rows if r.state == JobState.QUEUED]
            running = [r.id for r in rows if r.state == JobState.RUNNING]
            if queued:
                conn.execute(
                    sa.update(jobs)
                    .where(jobs.c.id.in_(queued))
                    .values(state=JobState.CANCELLED, finished_at=now, updated_at=now)
                )
            if running:
                conn.execute(
                    sa.update(jobs).where(jobs.c.id.in_(running)).values(cancel_requested=True, updated_at=now)
                )
            for job_id in queued:
                self._event(conn, job_id, "cancelled", now, reason="API key revoked")
            for job_id in running:
                self._event(conn, job_id, "cancel_requested", now, reason="API key revoked")
        return len(queued), len(running)

    # ------------------------------------------------------------------ owner-scoped actions
    def cancel(self, owner_key_id: str | None, job_id: str) -> JobRecord:
        """QUEUED -> CANCELLED now; RUNNING -> cancel flag (the worker stops at its next heartbeat)."""
        now = utcnow()
        with self.tx.write() as conn:
            state = self._owned_state(conn, owner_key_id, job_id)
            if state == JobState.QUEUED:
                values = {"state": JobState.CANCELLED, "finished_at": now, "updated_at": now}
                conn.execute(sa.update(jobs).where(jobs.c.id == job_id).values(**values))
                self._event(conn, job_id, "cancelled", now)
            elif state == JobState.RUNNING:
                conn.execute(
                    sa.update(jobs).where(jobs.c.id == job_id).values(cancel_requested=True, updated_at=now)
                )
                self._event(conn, job_id, "cancel_requested", now)
            elif state != JobState.CANCELLED:
                raise ConflictError(f"job {job_id} is {state}; only QUEUED or RUNNING jobs can be cancelled")
            return self._get(conn, job_id, owner_key_id)

    def retry(self, owner_key_id: str | None, job_id: str) -> JobRecord:
        """FAILED -> QUEUED with a fresh attempt budget (the error history is kept)."""
        now = utcnow()
        with self.tx.write() as conn:
            state = self._owned_state(conn, owner_key_id, job_id)
            if state != JobState.FAILED:
                raise ConflictError(f"job {job_id} is {state}; only FAILED jobs can be retried")
            conn.execute(
                sa.update(jobs)
                .where(jobs.c.id == job_id)
                .values(
                    state=JobState.QUEUED, attempt=1, not_before=None, cancel_requested=False, progress=None,
                    queued_at=now, started_at=None, finished_at=None, updated_at=now,
                )
            )  # fmt: skip
            self._event(conn, job_id, "retried", now)
            return self._get(conn, job_id, owner_key_id)

    def delete(self, owner_key_id: str | None, job_id: str) -> None:
        """Delete a finished job with its input and result (its events stay)."""
        now = utcnow()
        with self.tx.write() as conn:
            state = self._owned_state(conn, owner_key_id, job_id)
            if state in ACTIVE:
                raise ConflictError(f"job {job_id} is {state}; cancel it first (only finished jobs can be deleted)")
            conn.execute(sa.delete(inputs).where(inputs.c.job_id == job_id))
            conn.execute(sa.delete(results).where(results.c.job_id == job_id))
            conn.execute(sa.delete(artifacts).where(artifacts.c.job_id == job_id))
            conn.execute(sa.delete(jobs).where(jobs.c.id == job_id))
            self._event(conn, job_id, "deleted", now, state=state)

    # ------------------------------------------------------------------ batches
    def create_batch(self, owner_key_id: str, name: str, meta: dict[str, Any] | None = None) -> BatchRecord:
        batch_id, now = uuid.uuid4().hex, utcnow()
        with self.tx.write() as conn:
            conn.execute(
                sa.insert(batches).values(
                    id=batch_id, owner_key_id=owner_key_id, name=name[:200], meta=dict(meta or {}), created_at=now
                )
            )
            return self._batch_record(conn, self._owned_batch(conn, owner_key_id, batch_id))

    def get_batch(self, owner_key_id: str | None, batch_id: str) -> BatchRecord:
        """The batch with counts per state and the aggregate metrics of its SUCCEEDED jobs."""
        with self.tx.read() as conn:
            row = self._owned_batch(conn, owner_key_id, batch_id)
            summaries = conn.execute(
                sa.select(results.c.summary)
                .select_from(jobs.join(results, results.c.job_id == jobs.c.id))
                .where(jobs.c.batch_id == batch_id, jobs.c.state == JobState.SUCCEEDED)
            ).scalars()
            metrics = aggregate(summaries)
            record = self._batch_record(conn, row)
        return dataclasses.replace(record, metrics=metrics)

    def list_batches(
        self, owner_key_id: str, page_size: int = 50, page_token: str | None = None, outcome: str | None = None
    ) -> tuple[builtins.list[BatchRecord], str | None]:
        """Newest first, keyset-paginated on (created_at, id) like ``list``; counts, no metrics. ``outcome``
        keeps the batches with at least one job of that outcome."""
        page_size = max(1, min(page_size, MAX_PAGE_SIZE))
        query = sa.select(batches).where(batches.c.owner_key_id == owner_key_id)
        if outcome is not None:
            wanted = _known_outcome(outcome)
            of_batch = sa.select(jobs.c.id).where(jobs.c.batch_id == batches.c.id, jobs.c.outcome == wanted)
            query = query.where(of_batch.exists())
        if page_token is not None:
            created, last_id = _decode_page_token(page_token)
            query = query.where(
                sa.or_(
                    batches.c.created_at < created, sa.and_(batches.c.created_at == created, batches.c.id < last_id)
                )
            )
        query = query.order_by(batches.c.created_at.desc(), batches.c.id.desc()).limit(page_size + 1)
        with self.tx.read() as conn:
            rows = conn.execute(query).all()
            more = len(rows) > page_size
            rows = rows[:page_size]
            counts, outcomes = self._counts(conn, [r.id for r in rows])
        page = [_batch(r, counts.get(r.id, {}), outcomes.get(r.id, {})) for r in rows]
        return page, (_encode_page_token(page[-1].created_at, page[-1].id) if more else None)

    def batch_jobs(self, owner_key_id: str | None, batch_id: str) -> builtins.list[JobRecord]:
        """Every job of the batch with its result summary, oldest first (the per-sequence report)."""
        with self.tx.read() as conn:
            self._owned_batch(conn, owner_key_id, batch_id)
            rows = conn.execute(
                self._job_select().where(jobs.c.batch_id == batch_id).order_by(jobs.c.created_at, jobs.c.id)
            ).all()
        return [self._record(r) for r in rows]

    def cancel_batch(self, owner_key_id: str | None, batch_id: str) -> tuple[BatchRecord, int]:
        """Cancel every QUEUED job now and flag every RUNNING one (as ``cancel`` does for one job);
        returns (batch, jobs changed)."""
        now = utcnow()
        with self.tx.write() as conn:
            row = self._owned_batch(conn, owner_key_id, batch_id)
            active = conn.execute(
                self.tx.locked(
                    sa.select(jobs.c.id, jobs.c.state).where(
                        jobs.c.batch_id == batch_id, jobs.c.state.in_(ACTIVE), jobs.c.cancel_requested.is_(False)
                    )
                )
            ).all()
            queued = [r.id for r in active if r.state == JobState.QUEUED]
            running = [r.id for r in active if r.state == JobState.RUNNING]
            if queued:
                conn.execute(
                    sa.update(jobs)
                    .where(jobs.c.id.in_(queued), jobs.c.state == JobState.QUEUED)
                    .values(state=JobState.CANCELLED, finished_at=now, updated_at=now)
                )
            if running:
                conn.execute(
                    sa.update(jobs).where(jobs.c.id.in_(running)).values(cancel_requested=True, updated_at=now)
                )
            self._events(conn, now, [(j, "cancelled") for j in queued] + [(j, "cancel_requested") for j in running])
            return self._batch_record(conn, row), len(active)

    def retry_failed_batch(self, owner_key_id: str | None, batch_id: str) -> tuple[BatchRecord, int]:
        """Requeue every FAILED job of the batch with a fresh attempt budget (as ``retry``)."""
        now = utcnow()
        with self.tx.write() as conn:
            row = self._owned_batch(conn, owner_key_id, batch_id)
            failed = conn.execute(
                self.tx.locked(sa.select(jobs.c.id).where(jobs.c.batch_id == batch_id, jobs.c.state == JobState.FAILED))
            ).scalars().all()
            if failed:
                conn.execute(
                    sa.update(jobs)
                    .where(jobs.c.id.in_(failed), jobs.c.state == JobState.FAILED)
                    .values(
                        state=JobState.QUEUED, attempt=1, not_before=None, cancel_requested=False, progress=None,
                        queued_at=now, started_at=None, finished_at=None, updated_at=now,
                    )
                )  # fmt: skip
            self._events(conn, now, [(j, "retried") for j in failed])
            return self._batch_record(conn, row), len(failed)

    # ------------------------------------------------------------------ event streams
    def job_events_after(
        self, owner_key_id: str | None, job_id: str, after_id: int = 0, limit: int = EVENTS_PER_READ
    ) -> tuple[JobRecord, builtins.list[JobEventRecord]]:
        """The job (without summary) and its events with id > ``after_id``, oldest first. A job's events are
        written under its row lock, so their ids grow in commit order and ``after_id`` misses none."""
        with self.tx.read() as conn:
            row = conn.execute(self._job_select(with_summary=False).where(jobs.c.id == job_id)).first()
            if row is None or (owner_key_id is not None and row.owner_key_id != owner_key_id):
                raise NotFoundError(f"no job {job_id}")
            rows = conn.execute(
                sa.select(events)
                .where(events.c.job_id == job_id, events.c.id > after_id)
                .order_by(events.c.id)
                .limit(limit)
            ).all()
        return self._record(row), [_event_record(r) for r in rows]

    def batch_events_after(
        self, owner_key_id: str | None, batch_id: str, after_id: int = 0, limit: int = EVENTS_PER_READ
    ) -> tuple[BatchRecord, builtins.list[JobEventRecord], bool]:
        """The batch (counts), the events of its jobs with id > ``after_id`` (oldest first), and whether that is
        all of them. Events of different jobs are not ordered by one lock: on PostgreSQL a transaction can
        commit after a later id is visible, so only the prefix older than ``EVENT_LAG`` is returned there
        (a client resuming after the last id then misses nothing); SQLite commits in id order."""
        now = utcnow()
        with self.tx.read() as conn:
            record = self._batch_record(conn, self._owned_batch(conn, owner_key_id, batch_id))
            rows = conn.execute(
                sa.select(events)
                .select_from(events.join(jobs, jobs.c.id == events.c.job_id))
                .where(jobs.c.batch_id == batch_id, events.c.id > after_id)
                .order_by(events.c.id)
                .limit(limit)
            ).all()
        out = [_event_record(r) for r in rows]
        if self.tx.postgres:
            cutoff = now - EVENT_LAG
            settled = next((i for i, e in enumerate(out) if e.at > cutoff), len(out))
            return record, out[:settled], settled == len(out)
        return record, out, True

    # ------------------------------------------------------------------ helpers
    def _owned_batch(self, conn: Connection, owner_key_id: str | None, batch_id: str) -> Row[Any]:
        row = conn.execute(sa.select(batches).where(batches.c.id == batch_id)).first() if _PLAIN_ID.fullmatch(
            batch_id) else None
        if row is None or (owner_key_id is not None and row.owner_key_id != owner_key_id):
            raise NotFoundError(f"no batch {batch_id}")
        return row

    @staticmethod
    def _counts(
        conn: Connection, batch_ids: builtins.list[str]
    ) -> tuple[dict[str, dict[str, int]], dict[str, dict[str, int]]]:
        """Per batch: jobs per state, and SUCCEEDED jobs per outcome."""
        if not batch_ids:
            return {}, {}
        rows = conn.execute(
            sa.select(jobs.c.batch_id, jobs.c.state, jobs.c.outcome, sa.func.count())
            .where(jobs.c.batch_id.in_(batch_ids))
            .group_by(jobs.c.batch_id, jobs.c.state, jobs.c.outcome)
        ).all()
        states: dict[str, dict[str, int]] = {}
        outcomes: dict[str, dict[str, int]] = {}
        for batch_id, state, outcome, n in rows:
            per_state = states.setdefault(batch_id, {})
            per_state[state] = per_state.get(state, 0) + int(n)
            if state == JobState.SUCCEEDED:
                per_outcome = outcomes.setdefault(batch_id, {})
                key = outcome or OUTCOMES[-1]
                per_outcome[key] = per_outcome.get(key, 0) + int(n)
        return states, outcomes

    def _batch_record(self, conn: Connection, row: Row[Any]) -> BatchRecord:
        states, outcomes = self._counts(conn, [row.id])
        return _batch(row, states.get(row.id, {}), outcomes.get(row.id, {}))

    @staticmethod
    def _events(conn: Connection, now: datetime, items: builtins.list[tuple[str, str]]) -> None:
        if items:
            conn.execute(sa.insert(events), [{"job_id": j, "at": now, "kind": k, "detail": {}} for j, k in items])

    # ------------------------------------------------------------------ row helpers
    @staticmethod
    def _job_select(with_summary: bool = True) -> sa.Select[Any]:
        if not with_summary:
            return sa.select(jobs, sa.null().label("summary"))
        return sa.select(jobs, results.c.summary).select_from(jobs.outerjoin(results, results.c.job_id == jobs.c.id))

    def _get(self, conn: Connection, job_id: str, owner_key_id: str | None) -> JobRecord:
        _require_plain_id(job_id)
        row = conn.execute(self._job_select().where(jobs.c.id == job_id)).first()
        # Another key's job answers exactly like a missing one, so ids cannot be probed.
        if row is None or (owner_key_id is not None and row.owner_key_id != owner_key_id):
            raise NotFoundError(f"no job {job_id}")
        return self._with_files(conn, [self._record(row)])[0]

    @staticmethod
    def _with_files(conn: Connection, records: builtins.list[JobRecord]) -> builtins.list[JobRecord]:
        """The records with the names, types and sizes of their artifacts (one query for all SUCCEEDED ones)."""
        done = [r.id for r in records if r.state == JobState.SUCCEEDED]
        if not done:
            return records
        rows = conn.execute(
            sa.select(artifacts.c.job_id, artifacts.c.name, artifacts.c.content_type, artifacts.c.size_bytes)
            .where(artifacts.c.job_id.in_(done))
            .order_by(artifacts.c.job_id, artifacts.c.name)
        ).all()
        files: dict[str, builtins.list[Artifact]] = {}
        for r in rows:
            files.setdefault(r.job_id, []).append(Artifact(r.name, r.content_type, b"", r.size_bytes))
        return [dataclasses.replace(r, files=tuple(files.get(r.id, ()))) if r.id in files else r for r in records]

    def _owned_state(self, conn: Connection, owner_key_id: str | None, job_id: str) -> JobState:
        _require_plain_id(job_id)
        query = sa.select(jobs.c.state, jobs.c.owner_key_id).where(jobs.c.id == job_id)
        row = conn.execute(self.tx.locked(query)).first()
        if row is None or (owner_key_id is not None and row.owner_key_id != owner_key_id):
            raise NotFoundError(f"no job {job_id}")
        return JobState(row.state)

    def _record(self, row: Row[Any]) -> JobRecord:
        m = row._mapping
        return JobRecord(
            id=m["id"], owner_key_id=m["owner_key_id"], name=m["name"], state=JobState(m["state"]),
            priority=m["priority"], attempt=m["attempt"], max_attempts=self.settings.max_attempts,
            options=dict(m["options"]), num_frames=m["num_frames"], cancel_requested=bool(m["cancel_requested"]),
            progress=m["progress"], errors=list(m["errors"]), idempotency_key=m["idempotency_key"],
            payload_hash=m["payload_hash"], worker_id=m["worker_id"], lease_expires_at=m["lease_expires_at"],
            not_before=m["not_before"], created_at=m["created_at"], queued_at=m["queued_at"],
            started_at=m["started_at"], finished_at=m["finished_at"], updated_at=m["updated_at"], summary=m["summary"],
            batch_id=m["batch_id"], outcome=m["outcome"], outcome_detail=m["outcome_detail"],
        )  # fmt: skip


#: A page token is the keyset position after the page's last row: microseconds since 1970 (UTC) of its
#: created_at, a dot, its id. Every string of this form is a position, so the API states the form in its schema
#: and accepts any token matching it (clients treat tokens as opaque all the same); 17 digits stay within year 9999.
PAGE_TOKEN_PATTERN = r"^[0-9]{1,17}\.[A-Za-z0-9_-]{1,64}$"
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_MICROSECOND = timedelta(microseconds=1)


def _encode_page_token(created_at: datetime, row_id: str) -> str:
    return f"{(created_at - _EPOCH) // _MICROSECOND}.{row_id}"


#: Job ids are uuid4 hex; anything else (NUL, which PostgreSQL cannot even compare, control characters, a
#: megabyte of text) is answered like a missing job without reaching the database.
_PLAIN_ID = re.compile(r"[A-Za-z0-9_-]{1,64}")


def _require_plain_id(job_id: str) -> None:
    if not _PLAIN_ID.fullmatch(job_id):
        raise NotFoundError(f"no job {shown(job_id)}")


def _decode_page_token(token: str) -> tuple[datetime, str]:
    if not re.fullmatch(PAGE_TOKEN_PATTERN[1:-1], token):
        raise InvalidRequestError([FieldProblem("page_token", "is not a token this service issued")])
    micros, row_id = token.split(".", 1)
    return _EPOCH + int(micros) * _MICROSECOND, row_id


def _batch(row: Row[Any], counts: dict[str, int], outcomes: dict[str, int]) -> BatchRecord:
    full = {str(state): counts.get(state, 0) for state in JobState}
    per_outcome = {name: outcomes.get(name, 0) for name in OUTCOMES}
    return BatchRecord(row.id, row.owner_key_id, row.name, dict(row.meta), row.created_at, full, outcomes=per_outcome)


def _known_outcome(outcome: str) -> str:
    if outcome not in OUTCOMES:
        raise InvalidRequestError([FieldProblem("outcome", f"must be one of {', '.join(OUTCOMES)}")])
    return outcome


def _event_record(row: Row[Any]) -> JobEventRecord:
    return JobEventRecord(row.id, row.job_id, row.at, row.kind, dict(row.detail))
