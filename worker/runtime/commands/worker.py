"""``hoi-refine worker``: Ray worker actors on this machine or a cluster, each claiming jobs from the queue."""

from __future__ import annotations

import argparse
import logging
import threading
from typing import Any

from worker.runtime.commands.pool_options import add_pool_arguments, pool_config


def register(subparsers: Any) -> None:
    w = subparsers.add_parser(
        "worker",
        help="run refinement workers (Ray actors) that take jobs from the queue",
        description=(
            "Start a local Ray instance (or join --ray-address) and run N worker actors with C threads each. "
            "Each actor claims a job, refines it with a pool of C MuJoCo states, heartbeats from its own "
            "thread and writes the result. SIGINT/SIGTERM releases running jobs back to the queue."
        ),
    )
    add_pool_arguments(w, default_workers=1)
    w.set_defaults(func=_cmd_worker)


def _cmd_worker(args: argparse.Namespace) -> int:
    from worker.runtime.actor import configure_logging
    from worker.runtime.backoff import WorkerStopping
    from worker.runtime.pool import WorkerPool
    from worker.runtime.supervisor import stop_on_signals

    configure_logging(logging.INFO)
    stop = threading.Event()
    pool = WorkerPool(pool_config(args))
    with stop_on_signals(stop):
        try:
            pool.start(stop)
            # ray.init installs its own fatal-signal handler for SIGTERM (it aborts the process); ours again.
            with stop_on_signals(stop):
                pool.run_until(stop)
        except WorkerStopping:
            pass  # stopped while waiting for the database: nothing was started
        finally:
            pool.stop()
    return 0
