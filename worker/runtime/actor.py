"""The Ray worker actor: one process, one ``WorkerLoop``, one MuJoCo pool of C MjData (issue #5.1).

Ray options (DESIGN §2, "the database owns retries"): ``max_task_retries=0`` so Ray never re-runs the
long-lived ``run`` call itself (a re-run would be a second, unleased execution); ``max_restarts=-1`` so
Ray restarts an actor whose process died, and the pool driver (``worker.runtime.pool``) calls ``run``
again on it. The job that the dead process held is requeued by the queue once its lease expires.

``max_concurrency=4`` makes the actor threaded, so ``stop()``, ``status()`` and ``pid()`` are answered while
``run`` is busy (and while a duplicate ``run`` call waits for the first). The actor receives the driver's
``HOI_REFINE_*`` settings explicitly: on a cluster the actor's process does not inherit the driver's
environment.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from typing import Any

from worker.runtime.priority import lower_priority

log = logging.getLogger(__name__)


def configure_logging(level: int = logging.INFO) -> None:
    """One-line log records on stderr (Ray forwards actor stderr to the driver when asked)."""
    root = logging.getLogger()
    if not any(getattr(h, "_hoi_refine", False) for h in root.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s [pid %(process)d] %(message)s"))
        handler._hoi_refine = True  # type: ignore[attr-defined]
        root.addHandler(handler)
    root.setLevel(level)
    # Alembic's plugin set-up logs a line per plugin at INFO on every import of the migration machinery.
    logging.getLogger("alembic").setLevel(logging.WARNING)
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per health poll otherwise


class WorkerActor:
    """Plain class; ``remote_worker_class`` turns it into a Ray actor class."""

    def __init__(self, worker_id: str, threads: int, env: dict[str, str], job_kind: str = "refine") -> None:
        # Settings first: everything below reads them.
        os.environ.update(env)
        configure_logging()
        from common.database import create_engine_for
        from common.queue import JobQueue
        from common.settings import get_settings
        from worker.runtime.jobs import make_artifact_function, make_job_function
        from worker.runtime.loop import WorkerLoop

        get_settings.cache_clear()
        settings = get_settings()
        self.nice = settings.worker_nice
        lower_priority(self.nice)  # below the API on a shared machine (worker.runtime.priority)
        self.worker_id = worker_id
        self._run_lock = threading.Lock()
        self.engine = create_engine_for(settings.resolved_database_url())
        self.queue = JobQueue(self.engine, settings=settings)
        self.job_fn = make_job_function(job_kind, threads=threads)
        self.loop = WorkerLoop(
            self.queue,
            self.job_fn,
            worker_id=worker_id,
            lease_seconds=settings.lease_seconds,
            extra_progress={"threads": threads},
            artifact_fn=make_artifact_function(job_kind),
            # A worker holds ``threads`` CPUs (Ray's num_cpus): only with more than one does drawing a preview
            # beside the next job use cores its own rollouts leave idle instead of another worker's.
            overlap_preview=threads > 1,
            preview_nice=settings.preview_nice,
        )
        log.info("actor %s ready (pid %d, %d thread(s), job kind %s)", worker_id, os.getpid(), threads, job_kind)

    def run(self) -> dict[str, int]:
        # One loop per actor, even if Ray delivers a run call that the driver saw fail during a restart
        # (ActorUnavailableError means "may or may not have run"): a second call waits for the first.
        with self._run_lock:
            # Ray may run this call on a thread that existed before __init__ lowered the others.
            lower_priority(self.nice)
            return self.loop.run()

    def stop(self) -> None:
        self.loop.stop()

    def status(self) -> dict[str, Any]:
        return self.loop.status()

    def pid(self) -> int:
        return os.getpid()


def remote_worker_class(threads: int) -> Any:
    """``WorkerActor`` as a Ray actor class reserving ``threads`` CPUs."""
    import ray

    remote: Any = ray.remote  # its overloads do not cover the options-only form
    return remote(num_cpus=threads, max_restarts=-1, max_task_retries=0, max_concurrency=4)(WorkerActor)
