"""Reads, row helpers and API keys of the job queue: the base half of ``common.queue.JobQueue``.

Split from ``common.queue`` only for size; the two files are one class (``JobQueue`` derives from
``QueueBase``) and together hold every queue query (DESIGN §4). Use ``JobQueue``, not this class.
"""

from __future__ import annotations

import base64
import builtins
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime
from typing import Any, cast

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine, Row

from common import api_keys
from common.database import IMMEDIATE
from common.db_models import ACTIVE_STATES, ApiKey, Job, JobEvent, JobInput, JobResult, utcnow
from common.errors import (
    AuthenticationError,
    ConflictError,
    FieldProblem,
    InvalidRequestError,
    NotFoundError,
)
from common.queue_types import ApiKeyRecord, JobEventRecord, JobRecord, QueueStats
from common.settings import Settings, get_settings

# Core tables of the mapped models: the queue speaks SQL expressions, never ORM sessions.
jobs = cast(sa.Table, Job.__table__)
inputs = cast(sa.Table, JobInput.__table__)
results = cast(sa.Table, JobResult.__table__)
events = cast(sa.Table, JobEvent.__table__)
keys = cast(sa.Table, ApiKey.__table__)

MAX_PAGE_SIZE = 500
_VERSION_SQL = sa.text("SELECT owner_key_id, updated_at FROM jobs WHERE id = :job_id")
#: Shortest key prefix ``revoke_api_key`` accepts: ``hoi_`` and two characters of the random part.
MIN_REVOKE_PREFIX = len(api_keys.KEY_PREFIX) + 2


class QueueBase:
    """Transactions, owner-scoped reads, counts and API keys (see ``JobQueue``)."""

    def __init__(self, engine: Engine, settings: Settings | None = None) -> None:
        self.engine = engine
        self.settings = settings if settings is not None else get_settings()
        self._postgres = engine.dialect.name == "postgresql"

    # ------------------------------------------------------------------ transactions
    @contextmanager
    def _write(self) -> Iterator[Connection]:
        """A write transaction (BEGIN IMMEDIATE on SQLite, see ``common.database``)."""
        with self.engine.connect() as conn:
            conn.execution_options(**{IMMEDIATE: True})
            with conn.begin():
                yield conn

    @contextmanager
    def _read(self) -> Iterator[Connection]:
        with self.engine.connect() as conn, conn.begin():
            yield conn

    def _locked(self, query: sa.Select[Any], skip_locked: bool = False) -> sa.Select[Any]:
        # SQLite has no row locks; its BEGIN IMMEDIATE already holds the whole database.
        return query.with_for_update(skip_locked=skip_locked) if self._postgres else query

    @staticmethod
    def _event(conn: Connection, job_id: str, kind: str, now: datetime, **detail: Any) -> None:
        conn.execute(sa.insert(events).values(job_id=job_id, at=now, kind=kind, detail=detail))

    # ------------------------------------------------------------------ owner-scoped reads
    def get(self, owner_key_id: str | None, job_id: str) -> JobRecord:
        """The job with its summary; ``NotFoundError`` when missing or owned by another key (None = any)."""
        with self._read() as conn:
            return self._get(conn, job_id, owner_key_id)

    def version(self, owner_key_id: str | None, job_id: str) -> str:
        """An opaque version of the job: its ``updated_at`` as the driver returns it. Every write to a job sets
        ``updated_at``, so this versions the whole representation (the status poll's ETag and cache key).
        ``NotFoundError`` as ``get``.

        The status poll's hot path: one indexed single-row SELECT in autocommit (no BEGIN / ROLLBACK round
        trips), as plain SQL (no type processing: the value is only compared, never interpreted)."""
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
    ) -> tuple[builtins.list[JobRecord], str | None]:
        """Newest first, keyset-paginated on (created_at, id); returns (jobs, next_page_token)."""
        page_size = max(1, min(page_size, MAX_PAGE_SIZE))
        query = self._job_select(with_summary=False)
        if owner_key_id is not None:
            query = query.where(jobs.c.owner_key_id == owner_key_id)
        if state is not None:
            query = query.where(jobs.c.state == state)
        if batch_id is not None:
            query = query.where(jobs.c.batch_id == batch_id)
        if page_token is not None:
            created, last_id = _decode_page_token(page_token)
            query = query.where(
                sa.or_(jobs.c.created_at < created, sa.and_(jobs.c.created_at == created, jobs.c.id < last_id))
            )
        query = query.order_by(jobs.c.created_at.desc(), jobs.c.id.desc()).limit(page_size + 1)
        with self._read() as conn:
            page = [self._record(r) for r in conn.execute(query)]
        more = len(page) > page_size
        page = page[:page_size]
        return page, (_encode_page_token(page[-1].created_at, page[-1].id) if more else None)

    def get_result(self, owner_key_id: str | None, job_id: str) -> tuple[bytes, dict[str, Any]]:
        """(result NPZ bytes, summary) of a SUCCEEDED job; ``ConflictError`` before that."""
        with self._read() as conn:
            job = self._get(conn, job_id, owner_key_id)
            row = conn.execute(sa.select(results.c.result, results.c.summary).where(results.c.job_id == job_id)).first()
        if job.state != "SUCCEEDED" or row is None:
            raise ConflictError(f"job {job_id} is {job.state}; a result exists only once it has SUCCEEDED")
        return bytes(row.result), dict(row.summary)

    def get_payload(self, job_id: str) -> bytes:
        with self._read() as conn:
            blob = conn.execute(sa.select(inputs.c.payload).where(inputs.c.job_id == job_id)).scalar()
        if blob is None:
            raise NotFoundError(f"job {job_id} has no stored input")
        return bytes(blob)

    def events(self, owner_key_id: str | None, job_id: str) -> builtins.list[JobEventRecord]:
        with self._read() as conn:
            if owner_key_id is not None:
                self._get(conn, job_id, owner_key_id)
            rows = conn.execute(sa.select(events).where(events.c.job_id == job_id).order_by(events.c.id)).all()
        return [JobEventRecord(r.id, r.job_id, r.at, r.kind, dict(r.detail)) for r in rows]

    # ------------------------------------------------------------------ counts
    def count_active(self, owner_key_id: str) -> int:
        with self._read() as conn:
            return int(
                conn.execute(
                    sa.select(sa.func.count())
                    .select_from(jobs)
                    .where(jobs.c.owner_key_id == owner_key_id, jobs.c.state.in_(ACTIVE_STATES))
                ).scalar_one()
            )

    def stats(self, recent: int = 1000) -> QueueStats:
        """Jobs per state, claims so far, and queue-wait / run seconds of the ``recent`` latest started jobs."""
        with self._read() as conn:
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

    # ------------------------------------------------------------------ API keys
    def create_api_key(self, name: str) -> tuple[str, str]:
        """(key_id, plaintext). Only the key's SHA-256 is stored; the plaintext cannot be shown again."""
        key_id, plaintext = uuid.uuid4().hex, api_keys.new_key()
        with self._write() as conn:
            conn.execute(
                sa.insert(keys).values(
                    id=key_id, name=name[:200], key_hash=api_keys.hash_key(plaintext),
                    prefix=api_keys.display_prefix(plaintext), created_at=utcnow(),
                )
            )  # fmt: skip
        return key_id, plaintext

    def authenticate(self, plaintext: str) -> str:
        """The key id of a valid, unrevoked key; ``AuthenticationError`` otherwise ("API key revoked" for one
        that was revoked, so its holder learns why rather than suspecting a typo)."""
        with self._read() as conn:
            row = conn.execute(
                sa.select(keys.c.id, keys.c.revoked_at).where(keys.c.key_hash == api_keys.hash_key(plaintext))
            ).first()
        if row is not None and row.revoked_at is not None:
            raise AuthenticationError("API key revoked")
        return api_keys.require_key(None if row is None else row.id)

    def list_api_keys(self) -> builtins.list[ApiKeyRecord]:
        with self._read() as conn:
            rows = conn.execute(sa.select(keys).order_by(keys.c.created_at)).all()
        return [_key_record(r) for r in rows]

    def revoke_api_key(self, name_or_prefix: str) -> tuple[ApiKeyRecord, bool]:
        """Revoke the one key named by ``name_or_prefix``; returns (key, newly_revoked).

        It may be the key's id, its name, the start of its displayed prefix (``hoi_ab...``, at least
        ``MIN_REVOKE_PREFIX`` characters, so a stray letter cannot pick a key), or the key itself, whole or
        cut anywhere past the displayed prefix (what a leak report may quote).
        Unrevoked keys are matched first, so ``revoke alice`` picks alice's live key even if an old one of
        hers is already revoked. ``NotFoundError`` when nothing matches, ``ConflictError`` listing the
        candidates when several live keys do. When every match is revoked already nothing changes: the latest
        of them comes back with newly_revoked False.
        """
        wanted = name_or_prefix.strip().removesuffix("...")
        if not wanted:
            raise NotFoundError("name the key to revoke (its name, prefix or id)")
        digest = api_keys.hash_key(wanted)
        now = utcnow()
        with self._write() as conn:
            # Operators hold a handful of keys: match in Python (SQL LIKE would read the '_' of 'hoi_' as a
            # wildcard) over every row, locked so a concurrent revoke or create cannot slip in between.
            rows = conn.execute(self._locked(sa.select(keys).order_by(keys.c.created_at))).all()
            matches = [
                r for r in rows
                if r.id == wanted or r.name == wanted or r.key_hash == digest
                or (len(wanted) >= MIN_REVOKE_PREFIX and (r.prefix.startswith(wanted) or wanted.startswith(r.prefix)))
            ]  # fmt: skip
            if not matches:
                raise NotFoundError(f"no API key has the name, prefix or id {wanted!r} (see 'hoi-refine keys list')")
            live = [r for r in matches if r.revoked_at is None]
            if not live:  # nothing left to revoke: report the latest revocation
                return _key_record(max(matches, key=lambda r: r.revoked_at)), False
            if len(live) > 1:
                names = "; ".join(f"{r.id} {r.prefix}... {r.name!r}" for r in live)
                raise ConflictError(
                    f"{wanted!r} matches {len(live)} keys ({names}); name one by its id or a longer prefix"
                )
            (row,) = live
            conn.execute(sa.update(keys).where(keys.c.id == row.id).values(revoked_at=now))
            revoked = conn.execute(sa.select(keys).where(keys.c.id == row.id)).one()
        return _key_record(revoked), True

    # ------------------------------------------------------------------ row helpers
    @staticmethod
    def _job_select(with_summary: bool = True) -> sa.Select[Any]:
        if not with_summary:
            return sa.select(jobs, sa.null().label("summary"))
        return sa.select(jobs, results.c.summary).select_from(jobs.outerjoin(results, results.c.job_id == jobs.c.id))

    def _get(self, conn: Connection, job_id: str, owner_key_id: str | None) -> JobRecord:
        row = conn.execute(self._job_select().where(jobs.c.id == job_id)).first()
        # Another key's job answers exactly like a missing one, so ids cannot be probed.
        if row is None or (owner_key_id is not None and row.owner_key_id != owner_key_id):
            raise NotFoundError(f"no job {job_id}")
        return self._record(row)

    def _owned_state(self, conn: Connection, owner_key_id: str | None, job_id: str) -> str:
        query = sa.select(jobs.c.state, jobs.c.owner_key_id).where(jobs.c.id == job_id)
        row = conn.execute(self._locked(query)).first()
        if row is None or (owner_key_id is not None and row.owner_key_id != owner_key_id):
            raise NotFoundError(f"no job {job_id}")
        return str(row.state)

    def _record(self, row: Row[Any]) -> JobRecord:
        m = row._mapping
        return JobRecord(
            id=m["id"], owner_key_id=m["owner_key_id"], name=m["name"], state=m["state"], priority=m["priority"],
            attempt=m["attempt"], max_attempts=self.settings.max_attempts, options=dict(m["options"]),
            num_frames=m["num_frames"], cancel_requested=bool(m["cancel_requested"]), progress=m["progress"],
            errors=list(m["errors"]), idempotency_key=m["idempotency_key"], payload_hash=m["payload_hash"],
            worker_id=m["worker_id"], lease_expires_at=m["lease_expires_at"], not_before=m["not_before"],
            created_at=m["created_at"], queued_at=m["queued_at"], started_at=m["started_at"],
            finished_at=m["finished_at"], updated_at=m["updated_at"], summary=m["summary"], batch_id=m["batch_id"],
        )  # fmt: skip


def _key_record(row: Row[Any]) -> ApiKeyRecord:
    return ApiKeyRecord(row.id, row.name, row.prefix, row.created_at, row.revoked_at)


def _encode_page_token(created_at: datetime, job_id: str) -> str:
    return base64.urlsafe_b64encode(f"{created_at.isoformat()}|{job_id}".encode()).decode().rstrip("=")


def _decode_page_token(token: str) -> tuple[datetime, str]:
    try:
        raw = base64.urlsafe_b64decode(token + "=" * (-len(token) % 4)).decode()
        created, job_id = raw.split("|", 1)
        when = datetime.fromisoformat(created)
        if when.tzinfo is None or not job_id:
            raise ValueError("incomplete token")
        return when, job_id
    except (ValueError, UnicodeDecodeError) as exc:
        raise InvalidRequestError([FieldProblem("page_token", "is not a token this service issued")]) from exc
