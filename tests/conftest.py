"""Fixtures shared by every test package."""

from __future__ import annotations

import gc
import sys
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy.engine import make_url

from common.dexycb import shared_data_dir
from common.settings import get_settings


@pytest.fixture(autouse=True)
def _fresh_settings(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test gets its own var dir (SQLite file, caches) and re-reads settings."""
    monkeypatch.setenv("HOI_REFINE_VAR_DIR", str(tmp_path / "var"))
    get_settings.cache_clear()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data``; tests that need real recordings skip cleanly without it."""
    data = shared_data_dir()
    if data is None:
        pytest.skip("../shared/data is not present")
    return data


@pytest.fixture(scope="session")
def dexycb_dev_files(shared_data: Path) -> list[Path]:
    files = sorted((shared_data / "dexycb" / "dev").glob("*.npz"))
    if not files:
        pytest.skip("no DexYCB development files under ../shared/data")
    return files


#: nodeid -> the database a test runs on, for the tests parametrised over databases (``BACKENDS``).
_DATABASE_OF: dict[str, str] = {}
_DATABASES = ("sqlite", "postgres")


def pytest_report_header(config: pytest.Config) -> str:
    """Which databases this run tests (the PostgreSQL half needs a server: ``make test`` finds a local one)."""
    from tests.support.queue_fixtures import POSTGRES_ENV, postgres_base_url

    url = postgres_base_url()
    if url is None:
        return f"databases: SQLite only ({POSTGRES_ENV} is not set: the PostgreSQL tests skip)"
    return f"databases: SQLite and PostgreSQL ({make_url(url).render_as_string(hide_password=True)})"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        params = getattr(getattr(item, "callspec", None), "params", {})
        for value in params.values():
            if isinstance(value, str) and value in _DATABASES:
                _DATABASE_OF[item.nodeid] = value


def pytest_terminal_summary(terminalreporter: Any) -> None:
    """One line saying how many database-parametrised tests ran, and how many skipped, on each database."""
    counts = {name: {"ran": 0, "skipped": 0} for name in _DATABASES}
    for outcome in ("passed", "failed", "skipped"):
        for report in terminalreporter.stats.get(outcome, []):
            database = _DATABASE_OF.get(getattr(report, "nodeid", ""))
            if database is not None and (outcome == "skipped" or report.when == "call"):
                counts[database]["skipped" if outcome == "skipped" else "ran"] += 1
    if any(c["ran"] or c["skipped"] for c in counts.values()):
        shown = "; ".join(f"{name} ran {c['ran']}, skipped {c['skipped']}" for name, c in counts.items())
        terminalreporter.write_line(f"tests per database: {shown}")


# Fixtures for every test package: a database per test on SQLite and PostgreSQL (tests/support/queue_fixtures.py),
# a MANO-format test model (tests/support/mano.py), a short refinement and offscreen OpenGL (tests/support/visual.py).
pytest_plugins = ["tests.support.queue_fixtures", "tests.support.mano", "tests.support.visual"]


# CPython 3.11.7 and older keep the AST constructor's recursion depth in one interpreter-wide struct; a garbage
# collection inside it can hand the GIL to another thread that builds an AST too, and the first then raises
# "SystemError: AST constructor recursion depth mismatch" (python/cpython#106905, fixed in 3.11.8). Collecting
# the schemathesis module does exactly that: hypothesis parses lambda sources while schemathesis's ASGI portal
# threads are alive, and one CI run failed there. Pausing the garbage collector while pytest collects closes that
# window; collecting allocates little, and the collector is back on before the first test runs.
_AST_RACE_FIXED = sys.version_info >= (3, 11, 8)


def pytest_collection(session: pytest.Session) -> None:
    if not _AST_RACE_FIXED:
        gc.disable()


def pytest_collection_finish(session: pytest.Session) -> None:
    gc.enable()
