"""Options shared by ``hoi-refine worker`` and ``hoi-refine up``: how many worker actors, threads each, which Ray
cluster, and the ``PoolConfig`` they make."""

from __future__ import annotations

import argparse
import shlex
from typing import Any


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def add_pool_arguments(p: argparse.ArgumentParser, default_workers: int) -> None:
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
    add_ray_start_args(p, "with --ray-node: ")
    p.add_argument(
        "--health-file",
        default=None,
        help="touch this file every second while the worker pool is healthy (container health checks)",
    )


def parse_ray_start_args(text: str) -> tuple[str, ...]:
    try:
        return tuple(shlex.split(text))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a shell-quoted string ({exc})") from exc


def add_ray_start_args(p: argparse.ArgumentParser, prefix: str) -> None:
    """``--ray-start-args``: for ``worker``/``up`` (the node of ``--ray-node``) and ``ray-head``."""
    p.add_argument(
        "--ray-start-args",
        metavar="'ARGS'",
        type=parse_ray_start_args,
        default=(),
        help=prefix + "extra options for `ray start`, as one shell-quoted string (write it as "
        "--ray-start-args='--node-ip-address 127.0.0.2 --node-manager-port 16500 ...'); e.g. to pin the node's "
        "ports when several Ray nodes share one network namespace (containers on the host network, as in "
        "docker-compose.test.yml)",
    )


def pool_config(args: argparse.Namespace) -> Any:
    from worker.runtime.pool import PoolConfig

    return PoolConfig(
        workers=args.workers,
        threads_per_worker=args.threads_per_worker,
        ray_address=args.ray_address,
        job_kind=args.job_kind,
        log_to_driver=not args.quiet_actors,
        join_as_node=args.ray_node,
        health_file=args.health_file,
        node_start_args=args.ray_start_args,
    )
