"""Fixtures of the browser tests: the Chromium to drive and a deployment (API + worker) on a scratch folder."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.browser import Deployment, chromium_path


@pytest.fixture(scope="session")
def chromium() -> str:
    return chromium_path()


@pytest.fixture
def deployment(tmp_path: Path) -> Iterator[Deployment]:
    dep = Deployment(tmp_path)
    try:
        yield dep
    finally:
        dep.close()
