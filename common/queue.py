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
"""

from __future__ import annotations

import hashlib
import json
import secrets
import uuid
from datetime import datetime, timedelta
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Row

from common.db_models import ACTIVE_STATES, utcnow
from common.errors import (
    ConflictError,
    IdempotencyMismatchError,
    LeaseLostError,
    LimitExceededError,
)
from common.job_options import JobOptions
from common.queue_base import inputs, jobs, results
from common.queue_batches import BatchQueries
from common.queue_types import ClaimedJob, JobRecord
from common.queue_webhooks import WebhookQueries


def payload_hash(payload: bytes, options: JobOptions) -> str:
    """SHA-256 over the sequence bytes and the canonical options JSON (what an Idempotency-Key must match)."""
    options_json = json.dumps(options.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(payload + b"\x00" + options_json.encode()).hexdigest()


class JobQueue(BatchQueries, WebhookQueries):
    """Submit, claim, heartbeat, complete, fail, cancel, retry, requeue; owner-scoped reads and API keys
    (inherited from ``QueueBase``), batches and event streams (``BatchQueries``) and webhooks
    (``WebhookQueries``)."""

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
            with self._write() as conn:
                if self._postgres:
                    # Serialise one owner's submissions: the idempotency lookup and the active-jobs limit
                    # below then see every committed sibling (SQLite's BEGIN IMMEDIATE already does this).
                    conn.execute(sa.select(sa.func.pg_advisory_xact_lock(sa.func.hashtext(owner_key_id))))
                if batch_id is not None:
                    self._owned_batch(conn, owner_key_id, batch_id)
                if idempotency_key is not None:
                    existing = self._by_idempotency_key(conn, owner_key_id, idempotency_key)
                    if existing is not None:
                        match = self._idempotent_match(existing, digest)
                        return self._into_batch(conn, match, batch_id), False
                active = conn.execute(
                    sa.select(sa.func.count())
                    .select_from(jobs)
                    .where(jobs.c.owner_key_id == owner_key_id, jobs.c.state.in_(ACTIVE_STATES))
                ).scalar_one()
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
                        id=job_id, owner_key_id=owner_key_id, batch_id=batch_id, name=name[:200], state="QUEUED",
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
            with self._read() as conn:
                existing = self._by_idempotency_key(conn, owner_key_id, idempotency_key)
            if existing is None:
                raise
            if existing.batch_id != batch_id:
                raise
            return self._idempotent_match(existing, digest), False

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
    def _idempotent_match(existing: JobRecord, digest: str) -> JobRecord:
        if existing.payload_hash != digest:
            raise IdempotencyMismatchError(
                f"Idempotency-Key was already used for job {existing.id} with a different sequence or options"
            )
        return existing

    # ------------------------------------------------------------------ worker side
    def claim(
        self, worker_id: str, lease_seconds: float | None = None, now: datetime | None = None
    ) -> ClaimedJob | None:
        """Take the next runnable job (highest priority, oldest first) under a fresh lease, or None."""
        now = now or utcnow()
        lease = timedelta(seconds=lease_seconds if lease_seconds is not None else self.settings.lease_seconds)
        token = secrets.token_hex(16)
        pick = self._locked(
            sa.select(jobs.c.id)
            .where(jobs.c.state == "QUEUED", sa.or_(jobs.c.not_before.is_(None), jobs.c.not_before <= now))
            .order_by(jobs.c.priority.desc(), jobs.c.created_at, jobs.c.id)
            .limit(1),
            skip_locked=True,
        )
        with self._write() as conn:
            row = conn.execute(
                sa.update(jobs)
                .where(jobs.c.id == pick.scalar_subquery(), jobs.c.state == "QUEUED")
                .values(
                    state="RUNNING", lease_token=token, lease_expires_at=now + lease, worker_id=worker_id,
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
        held = (jobs.c.id == job_id, jobs.c.lease_token == lease_token, jobs.c.state == "RUNNING")
        with self._write() as conn:
            before = None
            if progress is not None:
                before = conn.execute(self._locked(sa.select(jobs.c.progress).where(*held))).first()
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
            self._locked(
                sa.select(jobs.c.attempt, jobs.c.errors, jobs.c.cancel_requested, jobs.c.worker_id).where(
                    jobs.c.id == job_id, jobs.c.lease_token == lease_token, jobs.c.state == "RUNNING"
                )
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

    def complete(self, job_id: str, lease_token: str, result: bytes, summary: dict[str, Any]) -> None:
        """Store the result and mark SUCCEEDED (token-checked)."""
        now = utcnow()
        with self._write() as conn:
            self._lease_row(conn, job_id, lease_token)
            conn.execute(sa.delete(results).where(results.c.job_id == job_id))
            conn.execute(
                sa.insert(results).values(
                    job_id=job_id, result=result, size_bytes=len(result), summary=summary, created_at=now
                )
            )
            self._settle(conn, job_id, lease_token, now=now, state="SUCCEEDED", finished_at=now)
            self._event(conn, job_id, "succeeded", now, result_bytes=len(result))

    def fail(self, job_id: str, lease_token: str, error: str, retryable: bool = False) -> None:
        """Record an error; retryable errors requeue with backoff until ``max_attempts``, then FAILED."""
        now = utcnow()
        with self._write() as conn:
            row = self._lease_row(conn, job_id, lease_token)
            self._after_attempt(conn, job_id, lease_token, row, error, retryable, now)

    def _after_attempt(
        self, conn: Connection, job_id: str, token: str, row: Row[Any], error: str, retryable: bool, now: datetime
    ) -> str:
        """Requeue (attempt + 1, backoff), cancel or fail a job whose attempt ended in ``error``."""
        errors = [*row.errors, {"attempt": row.attempt, "at": now.isoformat(), "error": error, "worker": row.worker_id}]
        if row.cancel_requested:
            state, extra = "CANCELLED", {"finished_at": now}
        elif retryable and row.attempt < self.settings.max_attempts:
            # DESIGN §2 backoff: retry_backoff_seconds * 2**(attempt-1) before the next claim.
            delay = self.settings.retry_backoff_seconds * 2 ** (row.attempt - 1)
            state = "QUEUED"
            extra = {"attempt": row.attempt + 1, "not_before": now + timedelta(seconds=delay), "queued_at": now}
        else:
            state, extra = "FAILED", {"finished_at": now}
        self._settle(conn, job_id, token, now=now, state=state, errors=errors, **extra)
        kind = {"QUEUED": "requeued", "FAILED": "failed", "CANCELLED": "cancelled"}[state]
        self._event(conn, job_id, kind, now, attempt=row.attempt, error=error)
        return state

    def acknowledge_cancel(self, job_id: str, lease_token: str) -> None:
        """The worker saw the cancel flag and stopped: RUNNING -> CANCELLED."""
        now = utcnow()
        with self._write() as conn:
            row = self._lease_row(conn, job_id, lease_token)
            if not row.cancel_requested:
                raise ConflictError(f"job {job_id}: cancellation was not requested")
            self._settle(conn, job_id, lease_token, now=now, state="CANCELLED", finished_at=now)
            self._event(conn, job_id, "cancelled", now, attempt=row.attempt)

    def release(self, job_id: str, lease_token: str) -> None:
        """Graceful shutdown: give the job back (QUEUED, same attempt), or CANCELLED if that was asked."""
        now = utcnow()
        with self._write() as conn:
            row = self._lease_row(conn, job_id, lease_token)
            if row.cancel_requested:
                self._settle(conn, job_id, lease_token, now=now, state="CANCELLED", finished_at=now)
                self._event(conn, job_id, "cancelled", now, attempt=row.attempt)
            else:
                self._settle(conn, job_id, lease_token, now=now, state="QUEUED", not_before=None, queued_at=now)
                self._event(conn, job_id, "released", now, attempt=row.attempt, worker_id=row.worker_id)

    def requeue_expired(self, now: datetime | None = None) -> int:
        """Requeue RUNNING jobs whose lease ran out (attempt + 1, backoff); FAILED after max attempts."""
        now = now or utcnow()
        with self._write() as conn:
            rows = conn.execute(
                self._locked(
                    sa.select(
                        jobs.c.id, jobs.c.lease_token, jobs.c.attempt, jobs.c.errors, jobs.c.cancel_requested,
                        jobs.c.worker_id,
                    ).where(jobs.c.state == "RUNNING", jobs.c.lease_expires_at < now),
                    skip_locked=True,
                )
            ).all()  # fmt: skip
            for row in rows:
                msg = f"lease expired (worker {row.worker_id} stopped heartbeating)"
                self._after_attempt(conn, row.id, row.lease_token, row, msg, True, now)
        return len(rows)

    # ------------------------------------------------------------------ owner-scoped actions
    def cancel(self, owner_key_id: str | None, job_id: str) -> JobRecord:
        """QUEUED -> CANCELLED now; RUNNING -> cancel flag (the worker stops at its next heartbeat)."""
        now = utcnow()
        with self._write() as conn:
            state = self._owned_state(conn, owner_key_id, job_id)
            if state == "QUEUED":
                values = {"state": "CANCELLED", "finished_at": now, "updated_at": now}
                conn.execute(sa.update(jobs).where(jobs.c.id == job_id).values(**values))
                self._event(conn, job_id, "cancelled", now)
            elif state == "RUNNING":
                conn.execute(
                    sa.update(jobs).where(jobs.c.id == job_id).values(cancel_requested=True, updated_at=now)
                )
                self._event(conn, job_id, "cancel_requested", now)
            elif state != "CANCELLED":
                raise ConflictError(f"job {job_id} is {state}; only QUEUED or RUNNING jobs can be cancelled")
            return self._get(conn, job_id, owner_key_id)

    def retry(self, owner_key_id: str | None, job_id: str) -> JobRecord:
        """FAILED -> QUEUED with a fresh attempt budget (the error history is kept)."""
        now = utcnow()
        with self._write() as conn:
            state = self._owned_state(conn, owner_key_id, job_id)
            if state != "FAILED":
                raise ConflictError(f"job {job_id} is {state}; only FAILED jobs can be retried")
            conn.execute(
                sa.update(jobs)
                .where(jobs.c.id == job_id)
                .values(
                    state="QUEUED", attempt=1, not_before=None, cancel_requested=False, progress=None,
                    queued_at=now, started_at=None, finished_at=None, updated_at=now,
                )
            )  # fmt: skip
            self._event(conn, job_id, "retried", now)
            return self._get(conn, job_id, owner_key_id)

    def delete(self, owner_key_id: str | None, job_id: str) -> None:
        """Delete a finished job with its input and result (its events stay)."""
        now = utcnow()
        with self._write() as conn:
            state = self._owned_state(conn, owner_key_id, job_id)
            if state in ACTIVE_STATES:
                raise ConflictError(f"job {job_id} is {state}; cancel it first (only finished jobs can be deleted)")
            conn.execute(sa.delete(inputs).where(inputs.c.job_id == job_id))
            conn.execute(sa.delete(results).where(results.c.job_id == job_id))
            conn.execute(sa.delete(jobs).where(jobs.c.id == job_id))
            self._event(conn, job_id, "deleted", now, state=state)
