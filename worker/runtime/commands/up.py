"""``hoi-refine up``: the HTTP API, a local Ray instance and N worker actors on this machine, one command."""

from __future__ import annotations

import argparse
import logging
from typing import Any

from worker.runtime.commands.pool_options import add_pool_arguments, pool_config


def register(subparsers: Any) -> None:
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
    add_pool_arguments(u, default_workers=2)
    u.add_argument("--host", default="127.0.0.1", help="API bind address (default 127.0.0.1)")
    u.add_argument("--port", type=int, default=8000, help="API port (default 8000)")
    u.set_defaults(func=_cmd_up)


def _cmd_up(args: argparse.Namespace) -> int:
    from worker.runtime.actor import configure_logging
    from worker.runtime.supervisor import UpConfig, run_up

    configure_logging(logging.INFO)
    return run_up(UpConfig(host=args.host, port=args.port, pool=pool_config(args)))
