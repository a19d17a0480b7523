"""The dashboard's browser tests: Debian's chromium driven by Playwright (``executable_path``; Playwright's own
browser download cannot work here), installed with apt where it is missing and possible, skipped otherwise; and a
deployment of the API (uvicorn in a thread over a SQLite file) with, on demand, one real worker loop."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from common.database import create_engine_for, upgrade_to_head
from common.queue import JobQueue
from common.settings import Settings

CHROMIUM = "/usr/bin/chromium"
#: Root in a container: no sandbox. No network here: nothing in the background may try to reach one.
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--autoplay-policy=no-user-gesture-required",
]  # fmt: skip


def _apt_install(package: str) -> None:
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    cmd = ["apt-get", "install", "-y", "-q", "--no-install-recommends", package]
    if subprocess.run(cmd, env=env, capture_output=True, timeout=900).returncode != 0:
        subprocess.run(["apt-get", "update", "-q"], env=env, capture_output=True, timeout=600)
        subprocess.run(cmd, env=env, capture_output=True, timeout=900)


def chromium_path() -> str:
    """Debian's chromium, installed with apt when missing and possible; otherwise the calling test skips."""
    pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
    path = shutil.which("chromium") or CHROMIUM
    if not Path(path).exists() and hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        try:
            _apt_install("chromium")
        except (OSError, subprocess.TimeoutExpired) as exc:
            pytest.skip(f"could not install chromium with apt: {exc}")
        path = shutil.which("chromium") or CHROMIUM
    if not Path(path).exists():
        pytest.skip("Debian's chromium is not installed and cannot be installed here (not root or no apt)")
    return path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Deployment:
    """The API (uvicorn in a thread) and, once ``start_worker`` is called, one worker loop in another thread."""

    def __init__(self, tmp: Path) -> None:
        import uvicorn

        from service.app import create_app

        url = f"sqlite:///{tmp / 'dashboard.sqlite3'}"
        upgrade_to_head(url)
        self.settings = Settings(lease_seconds=30.0, max_active_jobs_per_key=20)
        self.engine = create_engine_for(url)
        self.queue = JobQueue(self.engine, self.settings)
        self.port = _free_port()
        self.base_url = f"http://127.0.0.1:{self.port}"
        config = uvicorn.Config(create_app(self.settings, self.engine), host="127.0.0.1", port=self.port,
                                log_level="warning")  # fmt: skip
        self.server = uvicorn.Server(config)
        self.threads = [threading.Thread(target=self.server.run, daemon=True)]
        self.threads[0].start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            assert time.monotonic() < deadline, "the API server did not start"
            time.sleep(0.05)
        self.loop: Any = None

    def start_worker(self) -> None:
        from worker.runtime.jobs import RefineJob, refine_preview
        from worker.runtime.loop import WorkerLoop

        self.loop = WorkerLoop(JobQueue(self.engine, self.settings), RefineJob(1), "browser-test-worker",
                               lease_seconds=30.0, idle_poll_seconds=0.1, artifact_fn=refine_preview)  # fmt: skip
        self.threads.append(threading.Thread(target=self.loop.run, daemon=True))
        self.threads[-1].start()

    def close(self) -> None:
        if self.loop is not None:
            self.loop.stop()
        self.server.should_exit = True
        for t in self.threads:
            t.join(60)
        self.engine.dispose()


def use_key(page: Any, key: str) -> None:
    page.fill("#key", key)
    page.click("#use-key")
