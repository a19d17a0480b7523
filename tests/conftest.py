"""Fixtures shared by every test package."""

from __future__ import annotations

import gc
import sys
from pathlib import Path

import pytest

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
