"""``hoi-refine submit PATH... --api URL --key KEY [--format ...] [--concurrency N] [--wait] [--out DIR]
[--retry-failed]``.

Job options use the same flags as the local refine command (``--seed``, ``--keyframe-interval``,
``--max-generations``, ``--popsize``, ``--weights name=value,...``, ``--priority``). ``--api`` and ``--key``
default to ``HOI_REFINE_API_URL`` / ``HOI_REFINE_API_KEY`` so a key need not appear in the shell history.
Heavy imports stay inside the handler so ``hoi-refine --help`` stays fast.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

from common.errors import ConfigurationError
from common.job_options_cli import add_job_option_arguments, job_options_from_args

DEFAULT_OUT = Path("hoi-refine-submit")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "submit",
        help="submit a whole dataset (files, folders, a DexYCB root) to a hoi-refine service",
        description=(
            "Find the sequences under PATH... (native .npz/.json files, DexYCB development NPZs, folders searched "
            "recursively, DexYCB release roots), validate each locally, and submit it with an Idempotency-Key "
            "derived from its content and the options. Progress is kept in OUT/manifest.json: after a crash or "
            "Ctrl-C, run the same command again to resume without submitting anything twice. With --wait, "
            "results and contacts are downloaded into OUT/results/. At the end the batch's outcome (executable or "
            "not, and why not), its report URLs and its metrics are printed, and the report is saved as "
            "OUT/report.csv and OUT/report.parquet. Exit status: 0 all done, 1 some failed, 130 interrupted."
        ),
    )
    p.add_argument("paths", nargs="+", type=Path, metavar="PATH", help="sequence files or folders")
    p.add_argument("--api", default=os.environ.get("HOI_REFINE_API_URL"), help="service URL ($HOI_REFINE_API_URL)")
    p.add_argument("--key", default=os.environ.get("HOI_REFINE_API_KEY"), help="API key ($HOI_REFINE_API_KEY)")
    p.add_argument(
        "--format",
        dest="fmt",
        choices=("auto", "npz", "json", "dexycb"),
        default="auto",
        help="what PATH holds: auto (.npz/.json files and DexYCB roots), only npz, only json, or a DexYCB root",
    )
    p.add_argument("--concurrency", type=_positive_int, default=4, help="parallel requests (default 4)")
    p.add_argument("--wait", action="store_true", help="wait for every job and download results + contacts")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"manifest + results folder (default {DEFAULT_OUT})")
    p.add_argument("--poll-interval", type=float, default=2.0, help="longest pause between polls of a job (s)")
    p.add_argument(
        "--progress-every",
        type=float,
        default=30.0,
        metavar="SECONDS",
        help="when the output is not a terminal: print a progress line this often (default 30)",
    )
    p.add_argument(
        "--retry-failed",
        action="store_true",
        help="requeue jobs that ended FAILED (POST /v1/jobs/{id}:retry, once per run) instead of reporting them",
    )
    add_job_option_arguments(p, queue=True)
    p.set_defaults(func=_cmd_submit)


def _cmd_submit(args: argparse.Namespace) -> int:
    from common.settings import get_settings
    from service.submit.runner import SubmitConfig, run_submit

    if not args.api:
        raise ConfigurationError("no service URL: pass --api URL or set HOI_REFINE_API_URL")
    if not args.key:
        raise ConfigurationError("no API key: pass --key KEY or set HOI_REFINE_API_KEY")
    cfg = SubmitConfig(
        paths=list(args.paths),
        api_url=args.api,
        api_key=args.key,
        out_dir=args.out,
        options=job_options_from_args(args),
        fmt=args.fmt,
        concurrency=args.concurrency,
        wait=args.wait,
        poll_interval_s=max(0.05, args.poll_interval),
        max_frames=get_settings().max_frames,
        retry_failed=args.retry_failed,
        progress_every_s=max(0.1, args.progress_every),
    )
    return run_submit(cfg).exit_code
