"""Webhooks: registration, the delivery outbox and its log (``WebhookStore``; the job queue itself is
``common.queue.JobQueue``, API keys ``common.api_key_store.ApiKeyStore``).

A webhook never blocks a worker or the queue: workers only append ``job_events`` rows, as they always
did. ``fan_out`` (run by the dispatcher in the API process, ``service.webhook_dispatcher``) reads those
events after a cursor and writes one ``webhook_deliveries`` row per (webhook, event): the outbox. The
dispatcher claims due rows (``claim_deliveries``: a short lease, so a crashed dispatcher's claim comes due
again), sends them outside any transaction, and ``record_delivery`` marks each DELIVERED or schedules the
next attempt with exponential backoff until ``webhook_max_attempts``, then FAILED. Every attempt is logged.
"""

from __future__ import annotations

import builtins
import uuid
from datetime import datetime, timedelta
from typing import Any, cast

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine, Row

from common.database import Transactions
from common.db_models import EventCursor, Webhook, WebhookDelivery, utcnow
from common.errors import NotFoundError
from common.queue import EVENT_LAG, batches, events, jobs
from common.queue_types import BatchRecord, DeliveryRecord, DeliveryToSend, WebhookRecord
from common.settings import Settings, get_settings
from common.webhook_signing import new_secret
from common.webhook_targets import WebhookTargets

webhooks = cast(sa.Table, Webhook.__table__)
deliveries = cast(sa.Table, WebhookDelivery.__table__)
cursors = cast(sa.Table, EventCursor.__table__)

CURSOR = "webhooks"
#: ``job_events`` kinds that are job state changes, and the webhook event type each one is sent as.
EVENT_TYPES: dict[str, str] = {
    "submitted": "job.queued", "requeued": "job.queued", "released": "job.queued", "retried": "job.queued",
    "claimed": "job.running", "succeeded": "job.succeeded", "failed": "job.failed", "cancelled": "job.cancelled",
}  # fmt: skip
BATCH_EVENT_TYPES = ("batch.active", "batch.completed")
ALL_EVENT_TYPES: tuple[str, ...] = (*sorted(set(EVENT_TYPES.values())), *BATCH_EVENT_TYPES)
MAX_BACKOFF_S = 3600.0


class WebhookStore:
    """Webhook registration, fan-out of job events into the outbox, and delivery bookkeeping. Workers never
    touch it: it only reads ``job_events`` (and the jobs and batches they belong to)."""

    def __init__(self, engine: Engine, settings: Settings | None = None) -> None:
        self.engine = engine
        self.settings = settings if settings is not None else get_settings()
        self.tx = Transactions(engine)
        #: Where webhooks may go: checked at registration here and again by the dispatcher at each delivery.
        self.targets = WebhookTargets(self.settings.webhook_allow_targets)

    # ------------------------------------------------------------------ registration
    def create_webhook(
        self, owner_key_id: str, url: str, event_types: builtins.list[str] | None = None
    ) -> tuple[WebhookRecord, str]:
        """(webhook, secret). The secret signs every delivery; it is returned here only. A URL whose host is not
        a public address (nor allowed by the operator) is refused with a 422 naming ``url``."""
        self.targets.check_url(url)
        hook_id, secret, now = uuid.uuid4().hex, new_secret(), utcnow()
        with self.tx.write() as conn:
            conn.execute(
                sa.insert(webhooks).values(
                    id=hook_id, owner_key_id=owner_key_id, url=url, secret=secret,
                    event_types=sorted(set(event_types or [])), created_at=now,
                )
            )  # fmt: skip
            return _webhook(self._owned_webhook(conn, owner_key_id, hook_id)), secret

    def list_webhooks(self, owner_key_id: str) -> builtins.list[WebhookRecord]:
        with self.tx.read() as conn:
            rows = conn.execute(
                sa.select(webhooks).where(webhooks.c.owner_key_id == owner_key_id).order_by(webhooks.c.created_at)
            ).all()
        return [_webhook(r) for r in rows]

    def delete_webhook(self, owner_key_id: str | None, webhook_id: str) -> None:
        """Remove the webhook with its delivery log (nothing more is sent to it)."""
        with self.tx.write() as conn:
            self._owned_webhook(conn, owner_key_id, webhook_id)
            conn.execute(sa.delete(deliveries).where(deliveries.c.webhook_id == webhook_id))
            conn.execute(sa.delete(webhooks).where(webhooks.c.id == webhook_id))

    def webhook_deliveries(
        self, owner_key_id: str | None, webhook_id: str, limit: int = 100, before_id: int | None = None
    ) -> builtins.list[DeliveryRecord]:
        """The delivery log, newest first; ``before_id`` pages on (keyset on the id)."""
        query = sa.select(deliveries).where(deliveries.c.webhook_id == webhook_id)
        if before_id is not None:
            query = query.where(deliveries.c.id < before_id)
        with self.tx.read() as conn:
            self._owned_webhook(conn, owner_key_id, webhook_id)
            rows = conn.execute(query.order_by(deliveries.c.id.desc()).limit(max(1, min(limit, 500)))).all()
        return [_delivery(r) for r in rows]

    # ------------------------------------------------------------------ outbox
    def fan_out(self, now: datetime | None = None, limit: int = 500) -> int:
        """Turn the job events after the cursor into deliveries for the owners' webhooks; returns rows
        written. Job state changes become ``job.*`` events; a batch whose state moved (ACTIVE <-> COMPLETED)
        gets one ``batch.*`` event per change."""
        now = now or utcnow()
        with self.tx.read() as conn:
            last = conn.execute(sa.select(cursors.c.last_event_id).where(cursors.c.name == CURSOR)).scalar()
            newest = conn.execute(sa.select(sa.func.max(events.c.id))).scalar() or 0
        if last is not None and newest <= last:
            return 0  # the common case: nothing happened since the last look, and no write transaction
        cutoff = now - EVENT_LAG if self.tx.postgres else now
        written = 0
        with self.tx.write() as conn:
            last = conn.execute(
                self.tx.locked(sa.select(cursors.c.last_event_id).where(cursors.c.name == CURSOR))
            ).scalar()
            hooks: dict[str, builtins.list[Row[Any]]] = {}
            for hook in conn.execute(sa.select(webhooks)).all():
                hooks.setdefault(hook.owner_key_id, []).append(hook)
            if last is None or not hooks:
                # First run, or nobody listens: start from now (history is never replayed to a new webhook).
                self._set_cursor(conn, last, newest)
                return 0
            rows = conn.execute(
                sa.select(events, jobs.c.owner_key_id, jobs.c.batch_id, jobs.c.state)
                .select_from(events.outerjoin(jobs, jobs.c.id == events.c.job_id))
                .where(events.c.id > last)
                .order_by(events.c.id)
                .limit(limit)
            ).all()
            cursor = last
            touched: dict[str, datetime] = {}
            for row in rows:
                if row.at > cutoff:
                    break  # a prefix only: an older id may still be committing (PostgreSQL)
                cursor = row.id
                kind = EVENT_TYPES.get(row.kind)
                if kind is None or row.owner_key_id not in hooks:
                    continue
                data = {"job_id": row.job_id, "batch_id": row.batch_id, "event_id": row.id, "state": kind[4:].upper()}
                data.update({k: v for k, v in row.detail.items() if k in ("attempt", "error", "worker_id", "outcome")})
                written += self._enqueue(conn, hooks[row.owner_key_id], kind, row.at, data, now)
                if row.batch_id is not None:
                    touched[row.batch_id] = row.at
            for batch_id, at in touched.items():
                written += self._batch_transition(conn, hooks, batch_id, at, now)
            self._set_cursor(conn, last, cursor)
        return written

    def _batch_transition(
        self, conn: Connection, hooks: dict[str, builtins.list[Row[Any]]], batch_id: str, at: datetime, now: datetime
    ) -> int:
        row = conn.execute(self.tx.locked(sa.select(batches).where(batches.c.id == batch_id))).first()
        if row is None:
            return 0
        counts = {
            str(s): int(n)
            for s, n in conn.execute(
                sa.select(jobs.c.state, sa.func.count()).where(jobs.c.batch_id == batch_id).group_by(jobs.c.state)
            ).all()
        }
        state = BatchRecord(row.id, row.owner_key_id, row.name, {}, row.created_at, counts).state
        if state == row.notified_state or state == "EMPTY":
            return 0
        conn.execute(sa.update(batches).where(batches.c.id == batch_id).values(notified_state=state))
        data = {"batch_id": batch_id, "name": row.name, "state": state, "counts": counts}
        return self._enqueue(conn, hooks.get(row.owner_key_id, []), f"batch.{state.lower()}", at, data, now)

    @staticmethod
    def _enqueue(
        conn: Connection, hooks: builtins.list[Row[Any]], kind: str, at: datetime, data: dict[str, Any], now: datetime
    ) -> int:
        payload = {"type": kind, "timestamp": at.isoformat(), "data": data}
        rows = [
            {
                "webhook_id": h.id, "msg_id": f"msg_{uuid.uuid4().hex}", "event_type": kind, "payload": payload,
                "state": "PENDING", "attempts": 0, "next_attempt_at": now, "log": [], "created_at": now,
            }
            for h in hooks
            if (not h.event_types or kind in h.event_types) and h.created_at <= at
        ]  # fmt: skip
        if rows:
            conn.execute(sa.insert(deliveries), rows)
        return len(rows)

    @staticmethod
    def _set_cursor(conn: Connection, last: int | None, value: int) -> None:
        if last is None:
            conn.execute(sa.insert(cursors).values(name=CURSOR, last_event_id=value))
        elif value != last:
            conn.execute(sa.update(cursors).where(cursors.c.name == CURSOR).values(last_event_id=value))

    def claim_deliveries(self, limit: int = 20, now: datetime | None = None) -> builtins.list[DeliveryToSend]:
        """Due PENDING deliveries, each taken for one attempt: ``next_attempt_at`` moves past the send timeout,
        so nobody else sends it meanwhile and a dispatcher that died mid-send leaves it due again."""
        now = now or utcnow()
        lease = timedelta(seconds=self.settings.webhook_timeout_seconds * 2 + 5)  # the send's whole deadline, twice
        due = sa.select(deliveries.c.id).where(deliveries.c.state == "PENDING", deliveries.c.next_attempt_at <= now)
        with self.tx.read() as conn:
            if conn.execute(due.limit(1)).first() is None:
                return []  # the common case: no write transaction (on SQLite it would queue behind workers)
        with self.tx.write() as conn:
            rows = conn.execute(
                self.tx.locked(
                    sa.select(deliveries.c.id, deliveries.c.msg_id, deliveries.c.payload, deliveries.c.attempts,
                              deliveries.c.webhook_id)
                    .where(deliveries.c.state == "PENDING", deliveries.c.next_attempt_at <= now)
                    .order_by(deliveries.c.next_attempt_at, deliveries.c.id)
                    .limit(limit),
                    skip_locked=True,
                )
            ).all()  # fmt: skip
            if not rows:
                return []
            ids = [r.id for r in rows]
            conn.execute(
                sa.update(deliveries)
                .where(deliveries.c.id.in_(ids))
                .values(attempts=deliveries.c.attempts + 1, next_attempt_at=now + lease)
            )
            targets = {
                h.id: h
                for h in conn.execute(
                    sa.select(webhooks.c.id, webhooks.c.url, webhooks.c.secret).where(
                        webhooks.c.id.in_({r.webhook_id for r in rows})
                    )
                )
            }
        return [
            DeliveryToSend(r.id, targets[r.webhook_id].url, targets[r.webhook_id].secret, r.msg_id, dict(r.payload),
                           r.attempts + 1)
            for r in rows
            if r.webhook_id in targets
        ]  # fmt: skip

    def record_delivery(
        self, delivery_id: int, status: int | None, error: str | None, elapsed_ms: float, now: datetime | None = None
    ) -> str:
        """Log one attempt (2xx = delivered); otherwise retry after ``backoff * 2**(attempt-1)`` s until
        ``webhook_max_attempts``, then FAILED. Returns the delivery's new state."""
        now = now or utcnow()
        ok = status is not None and 200 <= status < 300 and error is None
        with self.tx.write() as conn:
            row = conn.execute(
                self.tx.locked(sa.select(deliveries.c.attempts, deliveries.c.log).where(deliveries.c.id == delivery_id))
            ).first()
            if row is None:
                return "GONE"  # its webhook was deleted meanwhile
            entry = {"at": now.isoformat(), "attempt": row.attempts, "status": status, "error": error,
                     "ms": round(elapsed_ms, 1)}  # fmt: skip
            values: dict[str, Any] = {"log": [*row.log, entry], "last_status": status,
                                      "last_error": None if error is None else error[:500]}  # fmt: skip
            if ok:
                values.update(state="DELIVERED", delivered_at=now)
            elif row.attempts >= self.settings.webhook_max_attempts:
                values.update(state="FAILED")
            else:
                delay = min(MAX_BACKOFF_S, self.settings.webhook_backoff_seconds * 2 ** (row.attempts - 1))
                values.update(next_attempt_at=now + timedelta(seconds=delay))
            conn.execute(sa.update(deliveries).where(deliveries.c.id == delivery_id).values(**values))
            return str(values.get("state", "PENDING"))

    def _owned_webhook(self, conn: Connection, owner_key_id: str | None, webhook_id: str) -> Row[Any]:
        row = conn.execute(sa.select(webhooks).where(webhooks.c.id == webhook_id)).first()
        if row is None or (owner_key_id is not None and row.owner_key_id != owner_key_id):
            raise NotFoundError(f"no webhook {webhook_id}")
        return row


def _webhook(row: Row[Any]) -> WebhookRecord:
    return WebhookRecord(row.id, row.owner_key_id, row.url, list(row.event_types), row.created_at)


def _delivery(row: Row[Any]) -> DeliveryRecord:
    return DeliveryRecord(
        row.id, row.webhook_id, row.msg_id, row.event_type, dict(row.payload), row.state, row.attempts,
        row.next_attempt_at, row.last_status, row.last_error, list(row.log), row.created_at, row.delivered_at,
    )  # fmt: skip
