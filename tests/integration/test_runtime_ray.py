"""``hoi-refine worker`` with real Ray actors and the physics-free self-test job (SQLite).

Proves the runtime half of issue #5 without the refinement: a SIGKILLed actor's job is requeued after its
lease and finished by another worker with attempt 2 and one result; SIGTERM releases the running job so
none is left RUNNING.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from common.api_key_store import ApiKeyStore
from common.database import create_engine_for, upgrade_to_head
from common.job_options import JobOptions
from common.queue import JobQueue
from common.settings import get_settings
from worker.runtime.jobs import SELFTEST_GENERATION_ENV

pytestmark = pytest.mark.slow

LEASE_S = 3.0


def _wait(pred: object, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():  # type: ignore[operator]
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def test_killed_actor_job_is_finished_elsewhere_and_sigterm_leaves_nothing_running(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, request: pytest.FixtureRequest
) -> None:
    url = f"sqlite:///{tmp_path / 'q.sqlite3'}"
    env = {
        **os.environ,
        "HOI_REFINE_DATABASE_URL": url,
        "HOI_REFINE_VAR_DIR": str(tmp_path / "var"),
        "HOI_REFINE_LEASE_SECONDS": str(LEASE_S),
        "HOI_REFINE_RETRY_BACKOFF_SECONDS": "0",
        SELFTEST_GENERATION_ENV: "0.2",
    }
    for key in ("HOI_REFINE_DATABASE_URL", "HOI_REFINE_LEASE_SECONDS", "HOI_REFINE_RETRY_BACKOFF_SECONDS"):
        monkeypatch.setenv(key, env[key])
    get_settings.cache_clear()
    # Ray's folder is a link to a short one in the system temp dir (this path is too long for its sockets).
    request.addfinalizer(lambda: shutil.rmtree((tmp_path / "var" / "ray").resolve(), ignore_errors=True))
    upgrade_to_head(url)
    q = JobQueue(create_engine_for(url))
    request.addfinalizer(q.engine.dispose)
    owner, _ = ApiKeyStore(q.engine).create("t")
    ids = [
        q.submit(owner, f"seq{i}".encode(), JobOptions(seed=i, max_generations=g), None, f"j{i}", 5)[0].id
        for i, g in enumerate([40, 40, 5])
    ]
    log_path = tmp_path / "worker.log"
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "common.cli", "worker", "--workers", "2", "--job-kind", "selftest"],
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
        )
    try:
        # Kill the process running the first job once it has made progress.
        _wait(lambda: (q.get(None, ids[0]).progress or {}).get("generation", 0) >= 2, 90, "job 0 progress")
        victim = q.get(None, ids[0]).progress
        assert victim is not None
        os.kill(int(victim["pid"]), signal.SIGKILL)
        _wait(lambda: all(q.get(None, i).state == "SUCCEEDED" for i in ids), 90, "all jobs to succeed")
        killed = q.get(None, ids[0])
        assert killed.attempt == 2 and killed.progress is not None and killed.progress["pid"] != victim["pid"]
        assert [q.get(None, i).attempt for i in ids[1:]] == [1, 1]
        for i in ids:
            assert [e.kind for e in q.events(None, i)].count("succeeded") == 1
        # SIGTERM in the middle of a job: the job is released (QUEUED, attempt unchanged), not left RUNNING.
        last = q.submit(owner, b"last", JobOptions(max_generations=200), None, "last", 5)[0].id
        _wait(lambda: (q.get(None, last).progress or {}).get("generation", 0) >= 1, 30, "last job to run")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0
        rec = q.get(None, last)
        assert rec.state == "QUEUED" and rec.attempt == 1
        assert "released" in [e.kind for e in q.events(None, last)]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log_path.read_text(errors="replace")
    assert "died" in text and "Ray restarts it" in text
    # Ray's own logs are under the deployment's var dir (a link to a short folder: this path is too long for
    # Ray's sockets), not in the system's temp folder.
    logs = tmp_path / "var" / "ray" / "session_latest" / "logs"
    assert logs.is_dir() and any(p.name.startswith("raylet") for p in logs.iterdir())
