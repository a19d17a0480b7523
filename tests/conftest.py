"""Fixtures shared by every test package."""

from __future__ import annotations

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
