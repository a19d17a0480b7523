"""API keys: high-entropy bearer tokens stored only as SHA-256 hashes (DESIGN §2, issue #4 item 4).

A key has 256 random bits, so a plain (unsalted) SHA-256 is enough: there is no dictionary to attack,
and the hash can be looked up by equality with an index. The plaintext is shown once, at creation.

``ApiKeyStore`` holds every query on the ``api_keys`` table (the jobs' queries live in
``common.queue.JobQueue``); the service authenticates with it, ``hoi-refine keys`` manages keys with it,
and ``hoi-refine up`` creates its development key with it.
"""

from __future__ import annotations

import builtins
import hashlib
import secrets
import uuid
from dataclasses import dataclass
from datetime import datetime
from typing import Any, cast

import sqlalchemy as sa
from sqlalchemy.engine import Engine, Row

from common.database import IMMEDIATE
from common.db_models import ApiKey, utcnow
from common.errors import AuthenticationError, ConflictError, FieldProblem, InvalidRequestError, NotFoundError
from common.safe_text import text_problem

KEY_PREFIX = "hoi_"
#: Shortest key prefix ``ApiKeyStore.revoke`` accepts: ``hoi_`` and two characters of the random part.
MIN_REVOKE_PREFIX = len(KEY_PREFIX) + 2

keys = cast(sa.Table, ApiKey.__table__)


@dataclass(frozen=True)
class ApiKeyRecord:
    """A key as ``hoi-refine keys list`` shows it (never its hash or plaintext)."""

    id: str
    name: str
    prefix: str
    created_at: datetime
    revoked_at: datetime | None


def new_key() -> str:
    return KEY_PREFIX + secrets.token_urlsafe(32)


def hash_key(plaintext: str) -> str:
    return hashlib.sha256(plaintext.encode()).hexdigest()


def display_prefix(plaintext: str) -> str:
    """The first characters, for telling keys apart in listings (not enough to guess the rest)."""
    return plaintext[: len(KEY_PREFIX) + 6]


class ApiKeyStore:
    """Create, list, revoke and authenticate API keys on one database."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        # Writes run as BEGIN IMMEDIATE on SQLite (see ``common.database``), like the queue's.
        self._writer = engine.execution_options(**{IMMEDIATE: True})

    def create(self, name: str) -> tuple[str, str]:
        """(key_id, plaintext). Only the key's SHA-256 is stored; the plaintext cannot be shown again."""
        if (why := text_problem(name, 200)) is not None:  # NUL would fail on PostgreSQL only: refuse everywhere
            raise InvalidRequestError([FieldProblem("name", why)])
        key_id, plaintext = uuid.uuid4().hex, new_key()
        with self._writer.begin() as conn:
            conn.execute(
                sa.insert(keys).values(
                    id=key_id, name=name[:200], key_hash=hash_key(plaintext), prefix=display_prefix(plaintext),
                    created_at=utcnow(),
                )
            )  # fmt: skip
        return key_id, plaintext

    def authenticate(self, plaintext: str) -> str:
        """The key id of a valid, unrevoked key; ``AuthenticationError`` otherwise ("API key revoked" for one
        that was revoked, so its holder learns why rather than suspecting a typo)."""
        with self.engine.connect() as conn:
            row = conn.execute(
                sa.select(keys.c.id, keys.c.revoked_at).where(keys.c.key_hash == hash_key(plaintext))
            ).first()
        if row is None:
            raise AuthenticationError("invalid or revoked API key")
        if row.revoked_at is not None:
            raise AuthenticationError("API key revoked")
        return str(row.id)

    def list(self) -> builtins.list[ApiKeyRecord]:
        with self.engine.connect() as conn:
            rows = conn.execute(sa.select(keys).order_by(keys.c.created_at)).all()
        return [_record(r) for r in rows]

    def revoke(self, name_or_prefix: str) -> tuple[ApiKeyRecord, bool]:
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
        digest = hash_key(wanted)
        now = utcnow()
        query = sa.select(keys).order_by(keys.c.created_at)
        if self.engine.dialect.name == "postgresql":  # SQLite's BEGIN IMMEDIATE already holds the database
            query = query.with_for_update()
        with self._writer.begin() as conn:
            # Operators hold a handful of keys: match in Python (SQL LIKE would read the '_' of 'hoi_' as a
            # wildcard) over every row, locked so a concurrent revoke or create cannot slip in between.
            rows = conn.execute(query).all()
            matches = [
                r for r in rows
                if r.id == wanted or r.name == wanted or r.key_hash == digest
                or (len(wanted) >= MIN_REVOKE_PREFIX and (r.prefix.startswith(wanted) or wanted.startswith(r.prefix)))
            ]  # fmt: skip
            if not matches:
                raise NotFoundError(f"no API key has the name, prefix or id {wanted!r} (see 'hoi-refine keys list')")
            live = [r for r in matches if r.revoked_at is None]
            if not live:  # nothing left to revoke: report the latest revocation
                return _record(max(matches, key=lambda r: r.revoked_at)), False
            if len(live) > 1:
                names = "; ".join(f"{r.id} {r.prefix}... {r.name!r}" for r in live)
                raise ConflictError(
                    f"{wanted!r} matches {len(live)} keys ({names}); name one by its id or a longer prefix"
                )
            (row,) = live
            conn.execute(sa.update(keys).where(keys.c.id == row.id).values(revoked_at=now))
            revoked = conn.execute(sa.select(keys).where(keys.c.id == row.id)).one()
        return _record(revoked), True


def _record(row: Row[Any]) -> ApiKeyRecord:
    return ApiKeyRecord(row.id, row.name, row.prefix, row.created_at, row.revoked_at)
