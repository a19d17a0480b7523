"""Batches and event streams of the job queue: part of ``common.queue.JobQueue`` (issue #20).

Split from ``common.queue`` only for size; ``JobQueue`` derives from this class and it holds every batch
query: create, read with counts and aggregate metrics, keyset listing, the per-sequence report rows,
cancel and retry-failed for the whole batch, and the ``job_events`` reads behind the server-sent events.
A batch of another key answers exactly like a missing one (404), as jobs do.
"""

from __future__ import annotations

import builtins
import dataclasses
import uuid
from datetime import datetime, timedelta
from typing import Any, cast

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Row

from common.batch_metrics import aggregate
from common.db_models import ACTIVE_STATES, JOB_STATES, Batch, utcnow
from common.errors import NotFoundError
from common.queue_base import MAX_PAGE_SIZE, QueueBase, _decode_page_token, _encode_page_token, events, jobs, results
from common.queue_types import BatchRecord, JobEventRecord, JobRecord

batches = cast(sa.Table, Batch.__table__)

#: Events one stream read returns at most (the stream asks again at once while a read comes back full).
EVENTS_PER_READ = 200
#: How old an event must be before a stream over several jobs (or the webhook fan-out) passes it on
#: PostgreSQL: by then every transaction that took a smaller id has committed.
EVENT_LAG = timedelta(seconds=2)


class BatchQueries(QueueBase):
    """Batch queries and event reads (see ``JobQueue``)."""

    # ------------------------------------------------------------------ batches
    def create_batch(self, owner_key_id: str, name: str, meta: dict[str, Any] | None = None) -> BatchRecord:
        batch_id, now = uuid.uuid4().hex, utcnow()
        with self._write() as conn:
            conn.execute(
                sa.insert(batches).values(
                    id=batch_id, owner_key_id=owner_key_id, name=name[:200], meta=dict(meta or {}), created_at=now
                )
            )
            return self._batch_record(conn, self._owned_batch(conn, owner_key_id, batch_id))

    def get_batch(self, owner_key_id: str | None, batch_id: str) -> BatchRecord:
        """The batch with counts per state and the aggregate metrics of its SUCCEEDED jobs."""
        with self._read() as conn:
            row = self._owned_batch(conn, owner_key_id, batch_id)
            summaries = conn.execute(
                sa.select(results.c.summary)
                .select_from(jobs.join(results, results.c.job_id == jobs.c.id))
                .where(jobs.c.batch_id == batch_id, jobs.c.state == "SUCCEEDED")
            ).scalars()
            metrics = aggregate(summaries)
            record = self._batch_record(conn, row)
        return dataclasses.replace(record, metrics=metrics)

    def list_batches(
        self, owner_key_id: str, page_size: int = 50, page_token: str | None = None
    ) -> tuple[builtins.list[BatchRecord], str | None]:
        """Newest first, keyset-paginated on (created_at, id) like ``list``; counts, no metrics."""
        page_size = max(1, min(page_size, MAX_PAGE_SIZE))
        query = sa.select(batches).where(batches.c.owner_key_id == owner_key_id)
        if page_token is not None:
            created, last_id = _decode_page_token(page_token)
            query = query.where(
                sa.or_(
                    batches.c.created_at < created, sa.and_(batches.c.created_at == created, batches.c.id < last_id)
                )
            )
        query = query.order_by(batches.c.created_at.desc(), batches.c.id.desc()).limit(page_size + 1)
        with self._read() as conn:
            rows = conn.execute(query).all()
            more = len(rows) > page_size
            rows = rows[:page_size]
            counts = self._counts(conn, [r.id for r in rows])
        page = [_batch(r, counts.get(r.id, {})) for r in rows]
        return page, (_encode_page_token(page[-1].created_at, page[-1].id) if more else None)

    def batch_jobs(self, owner_key_id: str | None, batch_id: str) -> builtins.list[JobRecord]:
        """Every job of the batch with its result summary, oldest first (the per-sequence report)."""
        with self._read() as conn:
            self._owned_batch(conn, owner_key_id, batch_id)
            rows = conn.execute(
                self._job_select().where(jobs.c.batch_id == batch_id).order_by(jobs.c.created_at, jobs.c.id)
            ).all()
        return [self._record(r) for r in rows]

    def cancel_batch(self, owner_key_id: str | None, batch_id: str) -> tuple[BatchRecord, int]:
        """Cancel every QUEUED job now and flag every RUNNING one (as ``cancel`` does for one job);
        returns (batch, jobs changed)."""
        now = utcnow()
        with self._write() as conn:
            row = self._owned_batch(conn, owner_key_id, batch_id)
            active = conn.execute(
                self._locked(
                    sa.select(jobs.c.id, jobs.c.state).where(
                        jobs.c.batch_id == batch_id, jobs.c.state.in_(ACTIVE_STATES), jobs.c.cancel_requested.is_(False)
                    )
                )
            ).all()
            queued = [r.id for r in active if r.state == "QUEUED"]
            running = [r.id for r in active if r.state == "RUNNING"]
            if queued:
                conn.execute(
                    sa.update(jobs)
                    .where(jobs.c.id.in_(queued), jobs.c.state == "QUEUED")
                    .values(state="CANCELLED", finished_at=now, updated_at=now)
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
        with self._write() as conn:
            row = self._owned_batch(conn, owner_key_id, batch_id)
            failed = conn.execute(
                self._locked(sa.select(jobs.c.id).where(jobs.c.batch_id == batch_id, jobs.c.state == "FAILED"))
            ).scalars().all()
            if failed:
                conn.execute(
                    sa.update(jobs)
                    .where(jobs.c.id.in_(failed), jobs.c.state == "FAILED")
                    .values(
                        state="QUEUED", attempt=1, not_before=None, cancel_requested=False, progress=None,
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
        with self._read() as conn:
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
        with self._read() as conn:
            record = self._batch_record(conn, self._owned_batch(conn, owner_key_id, batch_id))
            rows = conn.execute(
                sa.select(events)
                .select_from(events.join(jobs, jobs.c.id == events.c.job_id))
                .where(jobs.c.batch_id == batch_id, events.c.id > after_id)
                .order_by(events.c.id)
                .limit(limit)
            ).all()
        out = [_event_record(r) for r in rows]
        if self._postgres:
            cutoff = now - EVENT_LAG
            settled = next((i for i, e in enumerate(out) if e.at > cutoff), len(out))
            return record, out[:settled], settled == len(out)
        return record, out, True

    # ------------------------------------------------------------------ helpers
    def _owned_batch(self, conn: Connection, owner_key_id: str | None, batch_id: str) -> Row[Any]:
        row = conn.execute(sa.select(batches).where(batches.c.id == batch_id)).first()
        if row is None or (owner_key_id is not None and row.owner_key_id != owner_key_id):
            raise NotFoundError(f"no batch {batch_id}")
        return row

    @staticmethod
    def _counts(conn: Connection, batch_ids: builtins.list[str]) -> dict[str, dict[str, int]]:
        if not batch_ids:
            return {}
        rows = conn.execute(
            sa.select(jobs.c.batch_id, jobs.c.state, sa.func.count())
            .where(jobs.c.batch_id.in_(batch_ids))
            .group_by(jobs.c.batch_id, jobs.c.state)
        ).all()
        out: dict[str, dict[str, int]] = {}
        for batch_id, state, n in rows:
            out.setdefault(batch_id, {})[state] = int(n)
        return out

    def _batch_record(self, conn: Connection, row: Row[Any]) -> BatchRecord:
        return _batch(row, self._counts(conn, [row.id]).get(row.id, {}))

    @staticmethod
    def _events(conn: Connection, now: datetime, items: builtins.list[tuple[str, str]]) -> None:
        if items:
            conn.execute(sa.insert(events), [{"job_id": j, "at": now, "kind": k, "detail": {}} for j, k in items])


def _batch(row: Row[Any], counts: dict[str, int]) -> BatchRecord:
    full = {state: counts.get(state, 0) for state in JOB_STATES}
    return BatchRecord(row.id, row.owner_key_id, row.name, dict(row.meta), row.created_at, full)


def _event_record(row: Row[Any]) -> JobEventRecord:
    return JobEventRecord(row.id, row.job_id, row.at, row.kind, dict(row.detail))
