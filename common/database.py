"""Engines and migrations for SQLite (default, one machine) and PostgreSQL (``HOI_REFINE_DATABASE_URL``).

SQLite (DESIGN §2): WAL so readers never block the writer, ``busy_timeout`` so a writer waits for the
lock instead of failing, foreign keys on, and ``BEGIN IMMEDIATE`` for write transactions. The last uses
SQLAlchemy's documented pysqlite recipe ("Serializable isolation / Savepoints / Transactional DDL"): turn
off the driver's own transaction handling and emit BEGIN ourselves from the ``begin`` event. A write
transaction is one opened on a connection with the execution option ``sqlite_begin_immediate=True``
(``common.queue`` does that for every write); read transactions take a plain deferred ``BEGIN`` so status
polls never queue behind writers.

Migrations are run from code with the Alembic Config built here, so ``hoi-refine serve`` can upgrade an
installed package without an ``alembic.ini`` in the working directory.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine
from sqlalchemy.engine.url import make_url

from common.errors import DatabaseUnavailableError

if TYPE_CHECKING:
    from alembic.config import Config

#: Execution option that makes the next transaction on a SQLite connection ``BEGIN IMMEDIATE``.
IMMEDIATE = "sqlite_begin_immediate"
SQLITE_BUSY_TIMEOUT_MS = 30_000
MIGRATIONS_DIR = Path(__file__).resolve().parents[1] / "migrations"


def create_engine_for(url: str, **kwargs: Any) -> Engine:
    """An engine for ``url``; SQLite gets WAL, busy_timeout, foreign keys and BEGIN IMMEDIATE for writes."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite":
        kwargs.setdefault("pool_pre_ping", True)
        return sa.create_engine(url, **kwargs)
    if parsed.database and parsed.database != ":memory:":
        Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
    connect_args = kwargs.pop("connect_args", {})
    connect_args.setdefault("timeout", SQLITE_BUSY_TIMEOUT_MS / 1000)
    # Threads of one process (uvicorn's thread pool) share the pool; SQLite serialises them itself.
    connect_args.setdefault("check_same_thread", False)
    engine = sa.create_engine(url, connect_args=connect_args, **kwargs)

    @sa.event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, _record: Any) -> None:
        # Take transaction control away from pysqlite so the "begin" hook decides how to BEGIN.
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute("PRAGMA synchronous=NORMAL")  # durable in WAL mode except on power loss
        cursor.close()

    @sa.event.listens_for(engine, "begin")
    def _on_begin(conn: sa.Connection) -> None:
        options = conn.get_execution_options()
        if options.get("isolation_level") == "AUTOCOMMIT":
            return  # one statement, its own implicit transaction (the status poll's version read)
        conn.exec_driver_sql("BEGIN IMMEDIATE" if options.get(IMMEDIATE, False) else "BEGIN")

    return engine


# ---------------------------------------------------------------------- migrations


class Transactions:
    """Transactions on one engine, for the stores that speak SQL (``JobQueue``, ``WebhookStore``): writes take
    SQLite's database lock up front (BEGIN IMMEDIATE, so two writers never deadlock upgrading their read
    locks), and row locks exist on PostgreSQL only."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self.postgres = engine.dialect.name == "postgresql"

    @contextmanager
    def write(self) -> Iterator[Connection]:
        with self.engine.connect() as conn:
            conn.execution_options(**{IMMEDIATE: True})
            with conn.begin():
                yield conn

    @contextmanager
    def read(self) -> Iterator[Connection]:
        with self.engine.connect() as conn, conn.begin():
            yield conn

    def locked(self, query: sa.Select[Any], skip_locked: bool = False) -> sa.Select[Any]:
        """``SELECT ... FOR UPDATE [SKIP LOCKED]`` on PostgreSQL; unchanged on SQLite, which has no row locks
        (its BEGIN IMMEDIATE already holds the whole database)."""
        return query.with_for_update(skip_locked=skip_locked) if self.postgres else query


def alembic_config(url: str) -> Config:
    """Alembic config built in code (``script_location`` = this package's ``migrations``)."""
    # Alembic is imported only here and below: workers and claimers open engines without paying for it.
    from alembic.config import Config

    # Config's stdout default is bound when alembic is first imported; pass today's stream (tests swap it).
    cfg = Config(stdout=sys.stdout)
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    # ConfigParser interpolation: a literal % in a URL (escaped passwords, options) must be doubled.
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return cfg


@lru_cache(maxsize=1)
def head_revision() -> str | None:
    """The newest migration shipped with this code (read once: /readyz asks on every probe)."""
    from alembic.script import ScriptDirectory
    return ScriptDirectory.from_config(alembic_config("sqlite://")).get_current_head()


def current_revision(engine: Engine) -> str | None:
    from alembic.runtime.migration import MigrationContext
    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def is_at_head(engine: Engine) -> bool:
    return current_revision(engine) == head_revision()


def upgrade_to_head(url: str) -> None:
    from alembic import command
    command.upgrade(alembic_config(url), "head")


def wait_for_database(engine: Engine, timeout_s: float = 60.0, first_delay_s: float = 0.25) -> None:
    """Block until ``SELECT 1`` succeeds, with exponential backoff; ``DatabaseUnavailableError`` after timeout."""
    deadline = time.monotonic() + timeout_s
    delay = first_delay_s
    while True:
        try:
            with engine.connect() as conn:
                conn.exec_driver_sql("SELECT 1")
            return
        except sa.exc.OperationalError as exc:
            if time.monotonic() + delay > deadline:
                raise DatabaseUnavailableError(
                    f"database {engine.url.render_as_string(hide_password=True)} did not answer "
                    f"within {timeout_s:.0f} s: {exc.orig}"
                ) from exc
            time.sleep(delay)
            delay = min(delay * 2, 5.0)


def database_ready(engine: Engine) -> tuple[bool, str]:
    """(ready, reason) for ``/readyz``: reachable and migrated to head."""
    try:
        rev = current_revision(engine)
    except sa.exc.SQLAlchemyError as exc:
        return False, f"database unreachable: {type(exc).__name__}"
    head = head_revision()
    if rev != head:
        return False, f"database at revision {rev}, code expects {head}"
    return True, "ok"
