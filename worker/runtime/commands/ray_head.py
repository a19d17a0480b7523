"""``hoi-refine ray-head``: a Ray head node in the foreground for a multi-machine deployment."""

from __future__ import annotations

import argparse
from typing import Any

from worker.runtime.commands.pool_options import add_ray_start_args


def register(subparsers: Any) -> None:
    h = subparsers.add_parser(
        "ray-head",
        help="run a Ray head node for a multi-machine deployment (workers join it with --ray-address)",
        description="Start a Ray head node in the foreground (ray start --head --block). It offers no CPUs by "
        "default: 'hoi-refine worker --ray-address HEAD:PORT --ray-node' on each worker machine adds them.",
    )
    h.add_argument("--port", type=int, default=6379, help="GCS port (default 6379)")
    h.add_argument("--num-cpus", type=int, default=0, help="CPUs the head offers to actors (default 0)")
    add_ray_start_args(h, "")
    h.set_defaults(func=_cmd_ray_head)


def _cmd_ray_head(args: argparse.Namespace) -> int:
    import os

    from common.settings import get_settings
    from worker.runtime.pool import ray_executable, with_temp_dir

    cmd = [ray_executable(), "start", "--head", "--block", "--port", str(args.port), "--num-cpus", str(args.num_cpus)]
    # Its sessions and logs under the deployment's var dir (HOI_REFINE_VAR_DIR), unless --temp-dir is given.
    cmd += ["--include-dashboard", "false", "--disable-usage-stats",
            *with_temp_dir(args.ray_start_args, get_settings().var_dir)]  # fmt: skip
    # Replace this process: the container's stop signal then reaches `ray start --block` directly.
    os.execv(cmd[0], cmd)
