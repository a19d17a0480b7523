"""The Ray driver: starts (or joins) Ray, runs N worker actors, restarts their loops, stops them cleanly.

``hoi-refine worker`` and ``hoi-refine up`` both use ``WorkerPool``. Between polls the driver also calls
``requeue_expired`` so a job held by a dead worker goes back to QUEUED soon after its lease runs out, even
while every live worker is busy (issue #5.2).

Graceful stop (SIGINT/SIGTERM): each actor is told to stop; its running job stops within one CMA-ES
generation and is released to QUEUED without consuming an attempt. Whatever an actor still holds after
the grace period is released by the driver with the lease token the actor reported, so no job is left
RUNNING; only then is Ray shut down.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.errors import ConfigurationError, DatabaseUnavailableError, LeaseLostError
from common.settings import get_settings
from worker.runtime.backoff import Backoff, WorkerStopping, call_with_backoff, is_unreachable

log = logging.getLogger(__name__)

ENV_PREFIX = "HOI_REFINE_"
#: Wait before the n-th retry of ``ray start`` for this machine's node: n times this.
NODE_START_RETRY_SECONDS = 5.0
#: Ray's folder under the deployment's var dir: its sessions, with the logs in ``session_latest/logs``.
RAY_DIR_NAME = "ray"
#: A Unix socket's path holds at most this many bytes (Linux: 108 with the NUL; Ray checks it).
SOCKET_PATH_MAX = 107
#: What Ray adds below its temp dir to reach a socket: ``/session_<date>_<time>_<us>_<pid>`` (up to 45 bytes
#: with a 7-digit pid) and ``/sockets/plasma_store`` with an increment suffix (up to 24).
RAY_SOCKET_SUFFIX_BYTES = 69


@dataclass
class PoolConfig:
    workers: int = 1
    threads_per_worker: int = 1
    ray_address: str | None = None
    job_kind: str = "refine"
    #: Forward actor logs to this process's stderr.
    log_to_driver: bool = True
    #: Seconds actors get to release their jobs on stop.
    stop_grace_seconds: float = 20.0
    #: Start a Ray node here that joins ``ray_address`` and pin the actors to it (one container = one node).
    join_as_node: bool = False
    #: Touched after every healthy poll (container health checks read its age).
    health_file: str | None = None
    #: Extra ``ray start`` options for the node of ``join_as_node`` (e.g. its IP and ports, when several nodes
    #: share one network namespace).
    node_start_args: tuple[str, ...] = ()
    #: ``ray start`` attempts for that node before giving up.
    node_start_attempts: int = 3

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.threads_per_worker < 1:
            raise ValueError(f"threads_per_worker must be >= 1, got {self.threads_per_worker}")
        if self.join_as_node and not self.ray_address:
            raise ValueError("join_as_node needs ray_address (the head to join)")
        if self.node_start_attempts < 1:
            raise ValueError(f"node_start_attempts must be >= 1, got {self.node_start_attempts}")
        if self.node_start_args and not self.join_as_node:
            raise ValueError("node_start_args (--ray-start-args) apply only to the node of join_as_node (--ray-node)")


@dataclass
class _Slot:
    worker_id: str
    actor: Any
    run_ref: Any = None
    restarts: int = 0
    #: The actor died and its restarted process has not answered yet.
    down: bool = False
    pid: int | None = None
    #: A restart was just seen: the run call made during it may still fail once.
    stale_call: bool = False
    last_status: dict[str, Any] = field(default_factory=dict)


def _require_schema(engine: Any) -> None:
    from common.database import is_at_head

    if not is_at_head(engine):
        raise DatabaseUnavailableError(
            "the database schema is not at the migration head yet (the API migrates it when it starts: "
            "`hoi-refine serve`, or `hoi-refine up`)"
        )


def ray_executable() -> str:
    """The ``ray`` CLI installed beside this interpreter (falls back to PATH)."""
    import shutil
    import sys

    beside = Path(sys.executable).with_name("ray")
    return str(beside) if beside.exists() else (shutil.which("ray") or "ray")


def ray_temp_dir(var_dir: Path) -> Path:
    """Where a Ray node of this deployment keeps its sessions and logs: ``VAR/ray``.

    Ray puts its Unix sockets below this folder, and a socket path may hold at most ``SOCKET_PATH_MAX`` bytes.
    When ``VAR/ray`` is too long for that, Ray gets a short folder in the system temp dir named after the var dir
    (the same one on every start), and ``VAR/ray`` is a link to it, so the logs are still found under VAR.
    """
    wanted = var_dir.resolve() / RAY_DIR_NAME
    if len(str(wanted).encode()) + RAY_SOCKET_SUFFIX_BYTES <= SOCKET_PATH_MAX:
        wanted.mkdir(parents=True, exist_ok=True)
        return wanted
    digest = hashlib.sha256(str(wanted).encode()).hexdigest()[:12]
    short = Path(tempfile.gettempdir()) / f"hoi-refine-ray-{digest}"
    short.mkdir(mode=0o700, exist_ok=True)
    wanted.parent.mkdir(parents=True, exist_ok=True)
    if wanted.is_symlink() and wanted.resolve() != short.resolve():
        wanted.unlink()
    if not wanted.exists() and not wanted.is_symlink():
        wanted.symlink_to(short, target_is_directory=True)
    elif not wanted.is_symlink():
        log.warning("%s is a folder: Ray's logs go to %s (the path is too long for Ray's sockets)", wanted, short)
    return short


def with_temp_dir(start_args: tuple[str, ...], var_dir: Path) -> tuple[str, ...]:
    """``ray start`` options with ``--temp-dir`` under the var dir, unless the user gave one."""
    if any(a == "--temp-dir" or a.startswith("--temp-dir=") for a in start_args):
        return start_args
    return (*start_args, "--temp-dir", str(ray_temp_dir(var_dir)))


def actor_environment() -> dict[str, str]:
    """The driver's ``HOI_REFINE_*`` settings with paths made absolute (actors run elsewhere)."""
    settings = get_settings()
    env = {k: v for k, v in os.environ.items() if k.startswith(ENV_PREFIX)}
    env[f"{ENV_PREFIX}DATABASE_URL"] = settings.resolved_database_url()
    env[f"{ENV_PREFIX}VAR_DIR"] = str(settings.var_dir.resolve())
    return env


class WorkerPool:
    def __init__(self, config: PoolConfig) -> None:
        self.config = config
        self.slots: list[_Slot] = []
        self.started_ray = False
        self._queue: Any = None
        self._last_requeue = 0.0
        self._node_started = False

    # ------------------------------------------------------------------ start

    def start(self, stop: threading.Event | None = None) -> None:
        """Wait for a reachable, migrated database, start (or join) Ray and the actors."""
        import ray

        from common.database import create_engine_for
        from common.queue import JobQueue
        from worker.runtime.actor import remote_worker_class

        settings = get_settings()
        engine = create_engine_for(settings.resolved_database_url())
        self._queue = JobQueue(engine, settings=settings)
        call_with_backoff(lambda: _require_schema(engine), "schema check", Backoff(1.0, 10.0), stop=stop, logger=log)
        cfg = self.config
        if cfg.join_as_node:
            self._start_node(stop)
        if not ray.is_initialized():
            if cfg.ray_address:
                ray.init(address=cfg.ray_address, log_to_driver=cfg.log_to_driver)
            else:
                # Lean local start (2-core machines): no dashboard, exactly the CPUs the actors need; its sessions
                # and logs under the deployment's var dir.
                ray.init(
                    num_cpus=cfg.workers * cfg.threads_per_worker,
                    include_dashboard=False,
                    log_to_driver=cfg.log_to_driver,
                    configure_logging=False,
                    _temp_dir=str(ray_temp_dir(settings.var_dir)),
                )
                log.info("Ray's logs: %s", Path(settings.var_dir).resolve() / RAY_DIR_NAME / "session_latest" / "logs")
            self.started_ray = True
        cls = remote_worker_class(cfg.threads_per_worker)
        if cfg.join_as_node:
            from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

            here = ray.get_runtime_context().get_node_id()
            cls = cls.options(scheduling_strategy=NodeAffinitySchedulingStrategy(node_id=here, soft=False))
        env = actor_environment()
        host = os.uname().nodename
        for i in range(cfg.workers):
            worker_id = f"{host}-{os.getpid()}-w{i + 1}-{uuid.uuid4().hex[:6]}"
            actor = cls.remote(worker_id, cfg.threads_per_worker, env, cfg.job_kind)
            self.slots.append(_Slot(worker_id, actor))
        for slot in self.slots:
            slot.run_ref = slot.actor.run.remote()
        log.info(
            "started %d worker actor(s) x %d thread(s) on Ray%s",
            cfg.workers,
            cfg.threads_per_worker,
            f" at {cfg.ray_address}" if cfg.ray_address else " (local)",
        )

    def _start_node(self, stop: threading.Event | None = None) -> None:
        """``ray start --address HEAD``: this machine (container) joins the cluster as a node, retried.

        ``ray start`` gives a new node a fixed 30 s to register with the GCS; on a loaded machine it can miss that
        ("The current node timed out during startup"), so a failed start is cleaned up and tried again.
        """
        import subprocess

        cfg = self.config
        cpus = cfg.workers * cfg.threads_per_worker
        cmd = [ray_executable(), "start", "--address", str(cfg.ray_address), "--num-cpus", str(cpus)]
        cmd += ["--disable-usage-stats", *with_temp_dir(cfg.node_start_args, get_settings().var_dir)]
        for attempt in range(1, cfg.node_start_attempts + 1):
            log.info("joining Ray cluster %s as a node with %d CPU(s) (attempt %d)", cfg.ray_address, cpus, attempt)
            if subprocess.run(cmd, check=False).returncode == 0:
                self._node_started = True
                return
            # This machine's node only (what the failed start left behind): in a container it runs nothing else.
            subprocess.run([ray_executable(), "stop", "--force"], check=False)
            if attempt < cfg.node_start_attempts:
                delay = NODE_START_RETRY_SECONDS * attempt
                log.warning("could not join Ray cluster %s; retrying in %.0f s", cfg.ray_address, delay)
                if (stop or threading.Event()).wait(delay):
                    raise WorkerStopping("stopped while joining the Ray cluster")
        raise ConfigurationError(
            f"could not join the Ray cluster at {cfg.ray_address} as a node after {cfg.node_start_attempts} "
            "attempts (the `ray start` output above says why)"
        )

    def actor_pids(self, timeout: float = 30.0) -> dict[str, int]:
        import ray

        return {s.worker_id: int(ray.get(s.actor.pid.remote(), timeout=timeout)) for s in self.slots}

    # ------------------------------------------------------------------ supervise

    def poll(self, timeout: float = 1.0) -> None:
        """Wait up to ``timeout`` s; restart the loop of any actor whose ``run`` ended (crash or return)."""
        import ray

        refs = [s.run_ref for s in self.slots if s.run_ref is not None]
        if refs:
            ready, _ = ray.wait(refs, num_returns=len(refs), timeout=timeout)
        else:
            ready = []
            time.sleep(timeout)
        for slot in self.slots:
            if slot.run_ref is None:
                continue
            if slot.run_ref not in ready:
                if slot.pid is None or slot.down:
                    self._check_pid(slot)
                continue
            try:
                counts = ray.get(slot.run_ref)
                log.warning("worker %s returned %s; starting its loop again", slot.worker_id, counts)
            except Exception as exc:  # the process died; Ray restarts it (max_restarts=-1)
                stale = slot.stale_call and type(exc).__name__ == "ActorUnavailableError"
                slot.stale_call = False
                if stale:  # the run call made while it restarted: the restarted process never got it
                    log.debug("worker %s: run call from before the restart failed; calling again", slot.worker_id)
                elif not slot.down:
                    log.warning(
                        "worker %s (pid %s) is down (%s); Ray restarts it", slot.worker_id, slot.pid,
                        type(exc).__name__,
                    )
                # Calls made while it restarts fail (ActorUnavailableError): keep calling run until one holds.
                slot.down = not stale
            slot.run_ref = slot.actor.run.remote()
        self._requeue_expired()
        if self.config.health_file:
            from pathlib import Path

            Path(self.config.health_file).touch()

    @staticmethod
    def _check_pid(slot: _Slot) -> None:
        """Learn the actor's pid; a new pid after a death is a restart (logged once)."""
        import ray

        try:
            pid = int(ray.get(slot.actor.pid.remote(), timeout=0.5))
        except Exception:
            return
        if slot.pid is not None and pid != slot.pid:
            slot.restarts += 1
            log.warning(
                "worker %s was restarted by Ray: pid %d -> %d (restart %d)", slot.worker_id, slot.pid, pid,
                slot.restarts,
            )
            slot.stale_call = True
        slot.pid, slot.down = pid, False

    def _requeue_expired(self) -> None:
        lease = get_settings().lease_seconds
        now = time.monotonic()
        if self._queue is None or now - self._last_requeue < lease / 3.0:
            return
        self._last_requeue = now
        try:
            n = self._queue.requeue_expired()
        except Exception as exc:
            if not is_unreachable(exc):
                raise
            log.warning("database unreachable during requeue_expired (%s); will retry", type(exc).__name__)
            return
        if n:
            log.info("requeued %d job(s) whose lease expired", n)

    def run_until(self, stop: threading.Event, poll_seconds: float = 1.0) -> None:
        while not stop.is_set():
            self.poll(poll_seconds)

    # ------------------------------------------------------------------ stop

    def stop(self) -> None:
        """Stop every actor, release what they still hold, shut Ray down (if we started it)."""
        import ray

        if not self.slots:
            return
        grace = self.config.stop_grace_seconds
        log.info("stopping %d worker(s): running jobs are released to the queue", len(self.slots))
        for slot in self.slots:
            try:
                slot.actor.stop.remote()
            except Exception as exc:
                log.warning("could not signal worker %s: %s", slot.worker_id, exc)
        refs = [s.run_ref for s in self.slots if s.run_ref is not None]
        deadline = time.monotonic() + grace
        pending = refs
        while pending and time.monotonic() < deadline:
            _, pending = ray.wait(pending, num_returns=len(pending), timeout=min(1.0, grace))
        # Whatever is still held (an actor stuck in a long simulation step) is released by us.
        for slot in self.slots:
            if slot.run_ref is not None and slot.run_ref not in pending:
                continue
            self._release_leftover(slot)
        for slot in self.slots:
            try:
                ray.kill(slot.actor, no_restart=True)
            except Exception as exc:
                log.debug("kill %s: %s", slot.worker_id, exc)
        self.slots = []
        if self.started_ray:
            ray.shutdown()
            self.started_ray = False
        if self._node_started:
            import subprocess

            # This machine's node only: in a container it runs nothing else.
            subprocess.run([ray_executable(), "stop"], check=False)
            self._node_started = False
        log.info("workers stopped")

    def _release_leftover(self, slot: _Slot) -> None:
        import ray

        try:
            status = ray.get(slot.actor.status.remote(), timeout=5.0)
        except Exception as exc:
            log.warning("worker %s did not report its job (%s); its lease will expire", slot.worker_id, exc)
            return
        if not status.get("job_id"):
            return
        try:
            self._queue.release(status["job_id"], status["lease_token"])
            log.info("released job %s held by worker %s", status["job_id"], slot.worker_id)
        except LeaseLostError:
            pass  # the actor wrote its outcome after all
