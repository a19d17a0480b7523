"""``hoi-refine worker`` (Ray worker actors on this machine or a cluster) and ``hoi-refine up`` (API + workers).

Heavy imports (Ray, the queue) stay inside the handlers so ``hoi-refine --help`` stays fast.
"""

from __future__ import annotations

import argparse
import logging
import threading
from typing import Any


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _add_pool_arguments(p: argparse.ArgumentParser, default_workers: int) -> None:
    p.add_argument("--workers", type=_positive_int, default=default_workers, help="worker actors (one job each)")
    p.add_argument(
        "--threads-per-worker",
        type=_positive_int,
        default=1,
        help="CPU threads per actor: the size of its MjData pool for parallel CMA-ES evaluation",
    )
    p.add_argument(
        "--ray-address",
        default=None,
        help="join this Ray cluster (e.g. ray-head:6379) instead of starting a local Ray instance",
    )
    # Physics-free job for runtime diagnostics and tests; not part of the user-facing interface.
    p.add_argument("--job-kind", choices=("refine", "selftest"), default="refine", help=argparse.SUPPRESS)
    p.add_argument("--quiet-actors", action="store_true", help="do not forward actor logs to this terminal")
    p.add_argument(
        "--ray-node",
        action="store_true",
        help="with --ray-address: first start a Ray node on this machine that joins the cluster, and place this "
        "command's actors on it (one container = one node; used by docker-compose.yml)",
    )
    p.add_argument(
        "--health-file",
        default=None,
        help="touch this file every second while the worker pool is healthy (container health checks)",
    )


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
    _add_pool_arguments(w, default_workers=1)
    w.set_defaults(func=_cmd_worker)

    u = subparsers.add_parser(
        "up",
        help="API + local Ray + N workers on this machine (SQLite by default), one command",
        description=(
            "Start the HTTP API (migrating the database), a local Ray instance and N worker actors; print "
            "the URL and a development API key (kept in VAR_DIR/up-dev-key and reused while valid). Ctrl-C "
            "stops the workers (their jobs go back to QUEUED), then the API. The API is restarted if it "
            "crashes and dies with this command; one `up` per var dir, and one found dead there (killed) is "
            "cleared: its API stopped, its RUNNING jobs requeued."
        ),
    )
    _add_pool_arguments(u, default_workers=2)
    u.add_argument("--host", default="127.0.0.1", help="API bind address (default 127.0.0.1)")
    u.add_argument("--port", type=int, default=8000, help="API port (default 8000)")
    u.set_defaults(func=_cmd_up)

    h = subparsers.add_parser(
        "ray-head",
        help="run a Ray head node for a multi-machine deployment (workers join it with --ray-address)",
        description="Start a Ray head node in the foreground (ray start --head --block). It offers no CPUs by "
        "default: 'hoi-refine worker --ray-address HEAD:PORT --ray-node' on each worker machine adds them.",
    )
    h.add_argument("--port", type=int, default=6379, help="GCS port (default 6379)")
    h.add_argument("--num-cpus", type=int, default=0, help="CPUs the head offers to actors (default 0)")
    h.set_defaults(func=_cmd_ray_head)


def _pool_config(args: argparse.Namespace) -> Any:
    from worker.runtime.pool import PoolConfig

    return PoolConfig(
        workers=args.workers,
        threads_per_worker=args.threads_per_worker,
        ray_address=args.ray_address,
        job_kind=args.job_kind,
        log_to_driver=not args.quiet_actors,
        join_as_node=args.ray_node,
        health_file=args.health_file,
    )


def _cmd_worker(args: argparse.Namespace) -> int:
    from worker.runtime.actor import configure_logging
    from worker.runtime.backoff import WorkerStopping
    from worker.runtime.pool import WorkerPool
    from worker.runtime.supervisor import stop_on_signals

    configure_logging(logging.INFO)
    stop = threading.Event()
    pool = WorkerPool(_pool_config(args))
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


def _cmd_up(args: argparse.Namespace) -> int:
    from worker.runtime.actor import configure_logging
    from worker.runtime.supervisor import UpConfig, run_up

    configure_logging(logging.INFO)
    return run_up(UpConfig(host=args.host, port=args.port, pool=_pool_config(args)))


def _cmd_ray_head(args: argparse.Namespace) -> int:
    import os

    from worker.runtime.pool import ray_executable

    cmd = [ray_executable(), "start", "--head", "--block", "--port", str(args.port), "--num-cpus", str(args.num_cpus)]
    cmd += ["--include-dashboard", "false", "--disable-usage-stats"]
    # Replace this process: the container's stop signal then reaches `ray start --block` directly.
    os.execv(cmd[0], cmd)
