"""``hoi-refine up``: API + local Ray + N workers on one machine, one command (issue #5.3).

Order of start: the API (``hoi-refine serve``, a child process, which migrates the database to head),
then a development API key, then Ray and the worker actors in this process. Order of stop, on SIGINT or
SIGTERM: workers first (their running jobs are released to QUEUED, see ``worker.runtime.pool``), then
the API. The API child runs in its own session so a terminal's Ctrl-C reaches only this supervisor,
which then stops everything in that order.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType

import httpx

from common.errors import ConfigurationError
from common.settings import get_settings
from worker.runtime.pool import PoolConfig, WorkerPool

log = logging.getLogger(__name__)

HEALTH_PATHS = ("/readyz", "/healthz")


@dataclass
class UpConfig:
    host: str = "127.0.0.1"
    port: int = 8000
    pool: PoolConfig = field(default_factory=lambda: PoolConfig(workers=2))
    api_start_timeout_s: float = 60.0
    key_name: str = "development key (hoi-refine up)"


@contextmanager
def stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT/SIGTERM set ``stop`` instead of raising, so shutdown runs in order; restored on exit."""

    def handler(signum: int, _frame: FrameType | None) -> None:
        if stop.is_set():
            log.warning("second %s: still stopping, please wait", signal.Signals(signum).name)
        else:
            log.info("%s received: stopping", signal.Signals(signum).name)
        stop.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def hoi_refine_command() -> list[str]:
    """The ``hoi-refine`` console script of this interpreter's environment, else ``python -m common.cli``."""
    script = Path(sys.executable).with_name("hoi-refine")
    return [str(script)] if script.exists() else [sys.executable, "-m", "common.cli"]


def start_api(host: str, port: int) -> subprocess.Popen[bytes]:
    """``hoi-refine serve`` in its own session (Ctrl-C in a terminal reaches only the supervisor)."""
    cmd = [*hoi_refine_command(), "serve", "--host", host, "--port", str(port), "--no-migrate"]
    log.info("starting API: %s", " ".join(cmd))
    return subprocess.Popen(cmd, start_new_session=True, env=dict(os.environ))


def wait_for_api(base_url: str, proc: subprocess.Popen[bytes], timeout_s: float, stop: threading.Event) -> None:
    deadline = time.monotonic() + timeout_s
    with httpx.Client(timeout=2.0) as client:
        while time.monotonic() < deadline and not stop.is_set():
            if proc.poll() is not None:
                raise ConfigurationError(f"the API process exited with code {proc.returncode} during start-up")
            for path in HEALTH_PATHS:
                try:
                    if client.get(base_url + path).status_code == 200:
                        return
                except httpx.HTTPError:
                    break
            time.sleep(0.3)
    if not stop.is_set():
        raise ConfigurationError(f"the API did not answer at {base_url} within {timeout_s:.0f} s")


def create_dev_key(name: str) -> str:
    from common.database import create_engine_for
    from common.queue import JobQueue

    settings = get_settings()
    engine = create_engine_for(settings.resolved_database_url())
    try:
        _key_id, plaintext = JobQueue(engine, settings=settings).create_api_key(name)
    finally:
        engine.dispose()
    return str(plaintext)


def stop_api(proc: subprocess.Popen[bytes], timeout_s: float = 15.0) -> None:
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        log.warning("API did not stop within %.0f s; killing it", timeout_s)
        proc.kill()
        proc.wait()


def run_up(config: UpConfig, stop: threading.Event | None = None) -> int:
    """Run API + workers until ``stop`` is set (SIGINT/SIGTERM); returns an exit code."""
    stop = stop or threading.Event()
    base_url = f"http://{config.host}:{config.port}"
    pool = WorkerPool(config.pool)
    with stop_on_signals(stop):
        # Migrate here, once, so the API (started with --no-migrate) and Ray can start side by side.
        from common.database import upgrade_to_head

        upgrade_to_head(get_settings().resolved_database_url())
        api = start_api(config.host, config.port)
        try:
            pool.start()
            wait_for_api(base_url, api, config.api_start_timeout_s, stop)
            if stop.is_set():
                return 0
            key = create_dev_key(config.key_name)
            # The lines a user (and the acceptance test) reads: where the API is and how to call it.
            pool_cfg = config.pool
            print(f"workers: {pool_cfg.workers} x {pool_cfg.threads_per_worker} thread(s); Ctrl-C stops", flush=True)
            print(f"hoi-refine API: {base_url}  (docs: {base_url}/docs, dashboard: {base_url}/ui)", flush=True)
            print(f"development API key: {key}", flush=True)
            print(f"  export HOI_REFINE_API_URL={base_url} HOI_REFINE_API_KEY={key}", flush=True)
            # ray.init installs its own fatal-signal handler for SIGTERM (it aborts the process); ours again.
            with stop_on_signals(stop):
                while not stop.is_set():
                    pool.poll(1.0)
                    if api.poll() is not None:
                        log.error("the API process exited with code %s; stopping", api.returncode)
                        stop.set()
                        return 1
            return 0
        finally:
            pool.stop()
            stop_api(api)
            print("hoi-refine up: stopped", flush=True)
