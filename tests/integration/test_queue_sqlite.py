"""SQLite engine settings the queue relies on: WAL, busy_timeout, foreign keys, and BEGIN IMMEDIATE for the
queue's write transactions only (reads stay deferred, so polling never takes the write lock)."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from common.database import SQLITE_BUSY_TIMEOUT_MS, create_engine_for
from common.queue import JobQueue


def _try_write_lock(path: Path) -> bool:
    other = sqlite3.connect(path, timeout=0, isolation_level=None)
    try:
        other.execute("BEGIN IMMEDIATE")
        other.execute("ROLLBACK")
        return True
    except sqlite3.OperationalError as exc:
        assert "locked" in str(exc)
        return False
    finally:
        other.close()


def test_pragmas_and_write_transactions_take_the_lock_up_front(queue: JobQueue, db_url: str) -> None:
    path = Path(db_url.removeprefix("sqlite:///"))
    with queue.engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() == SQLITE_BUSY_TIMEOUT_MS
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    with queue.tx.write() as conn:
        conn.exec_driver_sql("SELECT 1")  # nothing written yet, but the write lock is already held
        assert not _try_write_lock(path)
    assert _try_write_lock(path)
    with queue.tx.read() as conn:
        conn.exec_driver_sql("SELECT count(*) FROM jobs")
        assert _try_write_lock(path)


def test_engine_creates_the_sqlite_folder(tmp_path: Path) -> None:
    engine = create_engine_for(f"sqlite:///{tmp_path / 'deep' / 'er' / 'q.sqlite3'}")
    with engine.connect() as conn:
        assert conn.exec_driver_sql("SELECT 1").scalar() == 1
    engine.dispose()
    assert (tmp_path / "deep" / "er" / "q.sqlite3").is_file()

