"""Fixtures for the queue, API and migration tests: a database per test on SQLite and on PostgreSQL,
tiny sequences, and fake results. Loaded for every test package through ``pytest_plugins`` in
``tests/conftest.py``.

PostgreSQL runs only when ``HOI_REFINE_TEST_POSTGRES_URL`` names a server (``.ci/run`` sets it when
127.0.0.1:5432 answers). Each test gets its own schema (``search_path`` in the URL, so subprocesses that
open the URL land in it too), dropped afterwards.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import sqlalchemy as sa

from common.api_key_store import ApiKeyStore
from common.database import create_engine_for, upgrade_to_head
from common.job_options import JobOptions
from common.queue import JobQueue
from common.result_format import write_result_npz
from common.sequence import HandTrack, ObjectSpec, Sequence
from common.sequence_io import sequence_to_npz_bytes
from common.settings import Settings

POSTGRES_ENV = "HOI_REFINE_TEST_POSTGRES_URL"
BACKENDS = ["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)]


def tiny_sequence(seed: int = 0, frames: int = 5, name: str = "tiny-box") -> Sequence:
    """A 4 cm box sliding 1 mm per frame and one right hand with random-ish keypoints around it."""
    rng = np.random.default_rng(seed)
    pose = np.zeros((frames, 7))
    pose[:, 0] = np.arange(frames) * 1e-3
    pose[:, 2] = 0.02
    pose[:, 3] = 1.0
    keypoints = rng.normal(scale=0.03, size=(frames, 21, 3)) + np.array([0.0, 0.0, 0.08])
    hand = HandTrack(side="right", valid=np.ones(frames, dtype=bool), keypoints=keypoints)
    obj = ObjectSpec(name="box", mass_kg=0.1, primitive="box", size=np.array([0.02, 0.02, 0.02]))
    return Sequence(name=name, fps=30.0, object=obj, object_pose=pose, hands=[hand], up=np.array([0.0, 0.0, 1.0]))


def tiny_payload(seed: int = 0) -> bytes:
    return sequence_to_npz_bytes(tiny_sequence(seed).validate())


def fake_result(frames: int = 5, contacts_per_frame: int = 2) -> tuple[bytes, dict[str, Any]]:
    """A result NPZ in the ``common.result_format`` layout with a few contacts per frame."""
    n = frames * contacts_per_frame
    rng = np.random.default_rng(1)
    arrays: dict[str, Any] = {
        "object_pose_sim": np.tile([0, 0, 0.02, 1, 0, 0, 0], (frames, 1)).astype(np.float64),
        "contact_frame": np.repeat(np.arange(frames), contacts_per_frame),
        "contact_hand": np.array(["right"] * n),
        "contact_body": np.array(["index3", "thumb3"] * frames),
        "contact_depth": np.full(n, 1e-4),
    }
    for key in ("contact_pos_world", "contact_pos_object", "contact_normal", "contact_force", "contact_torque"):
        arrays[key] = rng.normal(size=(n, 3))
    summary = {"metrics": {"raw": {"E_t_cm": 2.0}, "refined": {"E_t_cm": 0.5, "success": True}}, "seed": 0}
    return write_result_npz(arrays, summary), summary


def postgres_base_url() -> str | None:
    return os.environ.get(POSTGRES_ENV) or None


def _with_search_path(url: str, schema: str) -> str:
    sep = "&" if "?" in url else "?"
    return f"{url}{sep}options=-csearch_path%3D{schema}"


@contextmanager
def empty_database(backend: str, folder: Path) -> Iterator[str]:
    """The URL of an empty database on ``backend``: a SQLite file in ``folder``, or a fresh PostgreSQL schema
    (dropped afterwards; skips the test when no server is configured)."""
    if backend == "sqlite":
        yield f"sqlite:///{folder / 'queue.sqlite3'}"
        return
    base = postgres_base_url()
    if base is None:
        pytest.skip(f"{POSTGRES_ENV} is not set (no PostgreSQL server for this run)")
    schema = f"hoi_test_{uuid.uuid4().hex[:12]}"
    admin = sa.create_engine(base)
    with admin.begin() as conn:
        conn.exec_driver_sql(f"CREATE SCHEMA {schema}")
    try:
        yield _with_search_path(base, schema)
    finally:
        with admin.begin() as conn:
            conn.exec_driver_sql(f"DROP SCHEMA {schema} CASCADE")
        admin.dispose()


@pytest.fixture
def empty_db_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """An empty database (no tables) on the backend named by the test's ``backend`` parameter."""
    with empty_database(getattr(request, "param", "sqlite"), tmp_path) as url:
        yield url


@pytest.fixture
def db_url(empty_db_url: str) -> str:
    """A database migrated to head (through Alembic, as production does)."""
    upgrade_to_head(empty_db_url)
    return empty_db_url


@pytest.fixture
def queue_settings() -> Settings:
    return Settings(lease_seconds=30.0, max_attempts=3, retry_backoff_seconds=2.0, max_active_jobs_per_key=1000)


@pytest.fixture
def queue(db_url: str, queue_settings: Settings) -> Iterator[JobQueue]:
    engine = create_engine_for(db_url)
    try:
        yield JobQueue(engine, queue_settings)
    finally:
        engine.dispose()


@pytest.fixture
def keys(queue: JobQueue) -> ApiKeyStore:
    return ApiKeyStore(queue.engine)


@pytest.fixture
def owner(keys: ApiKeyStore) -> str:
    return keys.create("tests")[0]


def submit_tiny(queue: JobQueue, owner: str, seed: int = 0, key: str | None = None, priority: int = 0) -> str:
    job, _ = queue.submit(owner, tiny_payload(seed), JobOptions(seed=seed, priority=priority), key, "tiny", 5)
    return job.id



@dataclass
class ApiHarness:
    """The app on a real SQLite database, a TestClient, the queue behind it, and one API key."""

    client: Any
    queue: JobQueue
    keys: ApiKeyStore
    key_id: str
    headers: dict[str, str]

    def other_key_headers(self) -> dict[str, str]:
        _, plaintext = self.keys.create("another client")
        return {"Authorization": f"Bearer {plaintext}"}


@pytest.fixture
def api_settings() -> Settings:
    return Settings(max_frames=50, max_request_bytes=2_000_000, max_active_jobs_per_key=20, poll_retry_after_seconds=3)


@pytest.fixture
def api(db_url: str, api_settings: Settings) -> Iterator[ApiHarness]:
    from fastapi.testclient import TestClient

    from service.app import create_app

    engine = create_engine_for(db_url)
    app = create_app(api_settings, engine)
    queue: JobQueue = app.state.queue
    keys: ApiKeyStore = app.state.api_keys
    key_id, plaintext = keys.create("tests")
    with TestClient(app) as client:
        yield ApiHarness(client, queue, keys, key_id, {"Authorization": f"Bearer {plaintext}"})
    engine.dispose()
