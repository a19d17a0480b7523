"""``hoi-refine refine SEQ --out RESULT.npz``: windowed CMA-ES over spline keyframes (DESIGN §1.3-1.7); prints raw vs
refined metrics and writes one result NPZ."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from common.job_options_cli import add_job_option_arguments, job_options_from_args
from common.settings import get_settings
from worker.commands.inspect import add_object_dir_argument
from worker.commands.progress import ProgressBar


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "refine",
        help="optimise the hand motion of a sequence until the simulated object follows the recorded one",
        description="Windowed CMA-ES over spline keyframes: the hand's motion is optimised window by window until the "
        "simulated object, moved only through contact, follows the recorded one; writes one result NPZ.",
    )
    p.add_argument("sequence", type=Path, help="sequence file (.npz native or DexYCB, .json, DexYCB folder, ARCTIC "
                   ".npy)")
    p.add_argument("--out", type=Path, required=True, help="result file to write (.npz)")
    add_object_dir_argument(p)
    p.add_argument("--threads", type=int, default=1, help="simulation threads (default 1)")
    add_job_option_arguments(p)
    add_hand_arguments(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--no-wall-clock",
        action="store_true",
        help="leave the wall-clock timings (seconds, rates, thread count) out of the result file, for "
        "reproducibility checks: two runs with the same input, options and seed then give identical files "
        "(the step and evaluation counters stay)",
    )
    p.set_defaults(func=_refine)


def _refine(args: argparse.Namespace) -> int:
    from common.sequence_io import load_sequence
    from worker.refine.run import refine_sequence

    options = job_options_from_args(args)  # before loading: a bad flag should not wait for a slow load
    settings = get_settings()
    options = with_hand(options, args, settings.robot_dir)
    seq = load_sequence(args.sequence, object_dir=args.object_dir)
    bar = None if args.quiet else ProgressBar(options.restarts, options.polish)
    outcome = refine_sequence(seq, options, threads=args.threads, progress=bar,
                              cache_dir=settings.resolved_cache_dir(), mano_dir=settings.mano_dir)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_bytes(outcome.to_npz_bytes(wall_clock=not args.no_wall_clock))
    if bar is not None:
        bar.finish()
    print_refine_metrics(outcome.summary)
    print(f"wrote {args.out}")
    return 0


def add_hand_arguments(p: argparse.ArgumentParser) -> None:
    """``--hand`` and ``--robot-dir`` (issue #55)."""
    p.add_argument(
        "--hand", default=None,
        help="the hand that executes the motion: human (default, the built-in hand), allegro, leap (shipped "
        "correspondences; the models are read from --robot-dir) or a hand description file (JSON/YAML: model, "
        "actuated joints, keypoint correspondence; `hoi-refine hand check FILE` checks one)",
    )  # fmt: skip
    p.add_argument("--robot-dir", type=Path, default=None,
                   help="folder holding the robot models (a dex-urdf checkout); default HOI_REFINE_ROBOT_DIR")


def with_hand(options: Any, args: argparse.Namespace, robot_dir: Path | None) -> Any:
    """``options`` with ``--hand``'s description, packed (the model compiled and inlined)."""
    from worker.robot import resolve_hand

    hand = resolve_hand(args.hand, args.robot_dir or robot_dir)
    return options if hand is None else options.model_copy(update={"hand": hand})


def print_refine_metrics(summary: dict[str, Any]) -> None:
    """The outcome (executable, and why not), raw replay vs refined (``common.metrics_table``), then how the
    refinement ran."""
    from rich.console import Console

    from common.metrics_table import metrics_table, outcome_lines, run_footer

    for line in outcome_lines(summary):
        print(line)
    Console().print(metrics_table({"raw": summary["metrics"]["raw"], "refined": summary["metrics"]["refined"]}))
    print(run_footer(summary))
