"""``hoi-refine up``: API + local Ray + N workers on one machine, one command (issue #5.3).

Order of start: the deployment lock under the var dir (a dead ``up`` found there is cleared: its API
child stopped, its RUNNING jobs requeued; see ``worker.runtime.deployment_state``), the database
migration, the API (``hoi-refine serve``, a child process), Ray and the worker actors in this process,
then the development API key (reused from the last ``up`` while valid). Order of stop, on SIGINT or
SIGTERM: workers first (their running jobs are released to QUEUED, see ``worker.runtime.pool``), then
the API. The API child runs in its own session so a terminal's Ctrl-C reaches only this supervisor,
which then stops everything in that order; it dies with the supervisor (``PR_SET_PDEATHSIG``), and is
restarted (bounded) when it exits on its own.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from common.api_client import wait_until_ready
from common.errors import ApiError, AuthenticationError, ConfigurationError
from common.settings import get_settings
from common.stop_signals import stop_on_signals as common_stop_on_signals
from worker.runtime.deployment_state import (
    DeploymentRecord,
    DeploymentState,
    bind_listener,
    clear_stale,
    die_with_parent,
    process_start_time,
)
from worker.runtime.pool import PoolConfig, WorkerPool

T = TypeVar("T")

log = logging.getLogger(__name__)

HEALTH_PATHS = ("/readyz", "/healthz")


@dataclass
class UpConfig:
    host: str = "127.0.0.1"
    port: int = 8000
    pool: PoolConfig = field(default_factory=lambda: PoolConfig(workers=2))
    api_start_timeout_s: float = 60.0
    key_name: str = "development key (hoi-refine up)"
    #: A crashed API is restarted up to this many times within ``restart_window_s``; then ``up`` stops.
    max_api_restarts: int = 5
    restart_window_s: float = 600.0


def stop_on_signals(stop: threading.Event) -> AbstractContextManager[None]:
    """SIGINT/SIGTERM set ``stop`` instead of raising, so shutdown runs in order (a second one only says it is still
    stopping); restored on exit."""

    def say(sig: signal.Signals, again: bool) -> None:
        if again:
            log.warning("second %s: still stopping, please wait", sig.name)
        else:
            log.info("%s received: stopping", sig.name)

    return common_stop_on_signals(stop, say)


def hoi_refine_command() -> list[str]:
    """The ``hoi-refine`` console script of this interpreter's environment, else ``python -m common.cli``."""
    script = Path(sys.executable).with_name("hoi-refine")
    return [str(script)] if script.exists() else [sys.executable, "-m", "common.cli"]


def start_api(host: str, port: int, listener: socket.socket) -> subprocess.Popen[bytes]:
    """``hoi-refine serve`` on the supervisor's listening socket, in its own session (Ctrl-C in a terminal
    reaches only the supervisor), dying with the supervisor (``PR_SET_PDEATHSIG``) however the supervisor dies."""
    fd = listener.fileno()
    cmd = [*hoi_refine_command(), "serve", "--host", host, "--port", str(port), "--fd", str(fd), "--no-migrate"]
    log.info("starting API: %s", " ".join(cmd))
    return subprocess.Popen(
        cmd, start_new_session=True, env=dict(os.environ), preexec_fn=die_with_parent(), pass_fds=(fd,)
    )


class ApiChild:
    """The API process of ``up``: restarted when it exits, at most ``max_restarts`` times within
    ``restart_window_s`` (then ``up`` gives up), after a backoff of 1, 2, 4 ... s (at most 30 s)."""

    def __init__(
        self, config: UpConfig, state: DeploymentState, record: DeploymentRecord, listener: socket.socket
    ) -> None:
        self.config, self.state, self.record, self.listener = config, state, record, listener
        self.restarts: list[float] = []
        self._restart_at: float | None = None
        self.proc = self._start()

    def _start(self) -> subprocess.Popen[bytes]:
        proc = start_api(self.config.host, self.config.port, self.listener)
        self.record.api_pid, self.record.api_start_time = proc.pid, process_start_time(proc.pid)
        self.state.write(self.record)
        return proc

    def check(self) -> bool:
        """Restart the API if it exited (once its backoff has passed); False when restarts are used up."""
        if self.proc.poll() is None:
            return True
        now = time.monotonic()
        if self._restart_at is None:
            self.restarts = [t for t in self.restarts if now - t < self.config.restart_window_s]
            if len(self.restarts) >= self.config.max_api_restarts:
                log.error("the API process exited with code %s after %d restarts within %.0f s; stopping",
                          self.proc.returncode, len(self.restarts), self.config.restart_window_s)  # fmt: skip
                return False
            delay = min(2.0 ** len(self.restarts), 30.0)
            log.error("the API process exited with code %s; restarting it in %.0f s", self.proc.returncode, delay)
            self._restart_at = now + delay
        if now >= self._restart_at:
            self._restart_at = None
            self.restarts.append(now)
            self.proc = self._start()
            log.warning("API restarted (pid %s, restart %d)", self.proc.pid, len(self.restarts))
        return True


def wait_for_api(base_url: str, proc: subprocess.Popen[bytes], timeout_s: float, stop: threading.Event) -> None:
    try:
        wait_until_ready(base_url, timeout_s, alive=lambda: proc.poll() is None, stop=stop, paths=HEALTH_PATHS)
    except ApiError as exc:
        if proc.poll() is not None:
            raise ConfigurationError(f"the API process exited with code {proc.returncode} during start-up") from exc
        raise ConfigurationError(str(exc)) from exc


def _with_queue(fn: Callable[[Any], T]) -> T:
    from common.database import create_engine_for
    from common.queue import JobQueue

    engine = create_engine_for(get_settings().resolved_database_url())
    try:
        return fn(JobQueue(engine, settings=get_settings()))
    finally:
        engine.dispose()


def development_key(state: DeploymentState, name: str) -> str:
    """The key saved by an earlier ``up`` while it is still valid (jobs submitted with it stay readable
    after a restart), else a new one, saved for the next ``up``."""
    from common.api_key_store import ApiKeyStore
    from common.database import create_engine_for

    saved = state.saved_key()
    engine = create_engine_for(get_settings().resolved_database_url())
    try:
        store = ApiKeyStore(engine)
        if saved:
            try:
                store.authenticate(saved)
                return saved
            except AuthenticationError:
                log.info("the saved development key is revoked or unknown to this database: creating another")
        _key_id, key = store.create(name)
    finally:
        engine.dispose()
    state.save_key(key)
    return key


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
    settings = get_settings()
    state = DeploymentState(settings.var_dir)
    stale = state.acquire()  # refuses when another `up` runs from this var dir
    try:
        if stale is not None:
            clear_stale(stale)
        try:
            listener = bind_listener(config.host, config.port)
        except OSError as exc:
            raise ConfigurationError(f"port {config.port} on {config.host} is in use by another program; "
                                     "choose another with --port") from exc  # fmt: skip
        with listener:
            return _run(config, stop, base_url, state, stale, listener)
    finally:
        state.release()


def _run(
    config: UpConfig,
    stop: threading.Event,
    base_url: str,
    state: DeploymentState,
    stale: DeploymentRecord | None,
    listener: socket.socket,
) -> int:
    pool = WorkerPool(config.pool)
    with stop_on_signals(stop):
        # Migrate here, once, so the API (started with --no-migrate) and Ray can start side by side.
        from common.database import upgrade_to_head

        upgrade_to_head(get_settings().resolved_database_url())
        if stale is not None:
            # The dead deployment's workers died with it: their jobs go back to the queue now, not when
            # their leases run out.
            reason = f"the `hoi-refine up` (pid {stale.supervisor_pid}) running it died"
            n = _with_queue(lambda q: q.requeue_worker_jobs(stale.worker_prefix, reason))
            log.warning("requeued %d job(s) left RUNNING by the dead `hoi-refine up`", n)
        record = DeploymentRecord(os.getpid(), os.uname().nodename, base_url)
        api = ApiChild(config, state, record, listener)
        try:
            pool.start()
            wait_for_api(base_url, api.proc, config.api_start_timeout_s, stop)
            if stop.is_set():
                return 0
            key = development_key(state, config.key_name)
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
                    if not api.check():
                        stop.set()
                        return 1
            return 0
        finally:
            pool.stop()
            stop_api(api.proc)
            print("hoi-refine up: stopped", flush=True)
