"""The job-option flags shared by every command that starts refinements (``refine``, ``submit``).

One definition, so the flags, their help and their validation cannot drift apart between the local CLI and
the bulk client; ``JobOptions`` (``common.job_options``) stays the single contract behind them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from pydantic import ValidationError

from common.errors import FieldProblem, InputError
from common.hand_description import HandDescription, HandDescriptionError, check_packed, parse_hand_description
from common.job_options import LOSS_NAMES, JobOptions


def parse_weights(text: str) -> dict[str, float]:
    """``name=value,...`` -> loss weights (an argparse ``type``); names from ``LOSS_NAMES``."""
    weights: dict[str, float] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or name not in LOSS_NAMES:
            raise argparse.ArgumentTypeError(
                f"--weights wants name=value pairs with names from {', '.join(LOSS_NAMES)}; got {item!r}"
            )
        try:
            weights[name] = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"--weights: {name} needs a number, got {value!r}") from None
        if not weights[name] >= 0:
            raise argparse.ArgumentTypeError(f"--weights: {name} must be >= 0, got {value}")
    return weights


def add_job_option_arguments(parser: argparse.ArgumentParser, queue: bool = False) -> None:
    """Add the ``JobOptions`` flags; ``queue`` also adds ``--priority`` (meaningful only to the service)."""
    g = parser.add_argument_group("job options (the same as the API's options object)")
    g.add_argument("--seed", type=int, default=0, help="CMA-ES seed (default 0)")
    g.add_argument("--keyframe-interval", type=int, default=None, help="frames between keyframes (default fps/6)")
    g.add_argument("--max-generations", type=int, default=None, help="CMA-ES generations per window")
    g.add_argument("--popsize", type=int, default=None, help="CMA-ES population size")
    g.add_argument(
        "--weights", type=parse_weights, default={},
        help=f"loss weights, e.g. object_pose=2,hand_joints=0.5 (names: {', '.join(LOSS_NAMES)}; 0 disables a term)",
    )  # fmt: skip
    g.add_argument("--free-wrist-translation", action="store_true", help="also optimise a wrist translation offset")
    restarts = JobOptions.model_fields["restarts"].default  # the contract's default, stated once
    g.add_argument(
        "--restarts", type=int, default=restarts,
        help="refine again when the result fails (every frame within 3 cm / 30 deg) or the first attempt's object "
        "error is above the published method's mean (0.67 cm + 2.97 deg): with the lookahead's rotation error "
        f"charged, the job's seed then others, up to N times, keeping the best (default {restarts}; 0 disables)",
    )  # fmt: skip
    g.add_argument(
        "--no-polish", dest="polish", action="store_false",
        help="skip the polish sweeps over the best attempt's windows (run when its object error is above half the "
        "published method's mean; each keyframe optimised again with the later ones in view, kept only if better, "
        "repeated while kept, at most 10)",
    )  # fmt: skip
    g.add_argument(
        "--local-repair", action="store_true",
        help="with two hands or an articulated object: polish a failed attempt by re-optimising only the keyframes "
        "around its first frame past the success limit, instead of sweeping the whole sequence (default off)",
    )  # fmt: skip
    g.add_argument(
        "--bounded-tail", dest="tail", action="store_const", const="bounded", default="full",
        help="skip the rest of the plan (attempts, polish, rescue) when the first attempt fails at a recorded step "
        "no grasp can follow; the outcome then says plan_cut_short (default: the whole plan runs)",
    )  # fmt: skip
    g.add_argument(
        "--evaluation-budget", type=int, default=None, metavar="N",
        help="start no further attempt, polish sweep or rescue once N candidate evaluations are spent (the first "
        "attempt always runs whole; default: no budget)",
    )  # fmt: skip
    if queue:
        g.add_argument("--priority", type=int, default=0, help="queue priority, -100..100 (higher runs first)")
        g.add_argument(
            "--hand", type=Path, default=None, dest="hand_file",
            help="a packed robot hand description (JSON; `hoi-refine hand pack allegro|leap|FILE --out F` makes one) "
            "that every job's motion is refined for; default the built-in human hand",
        )  # fmt: skip
        g.add_argument(
            "--no-preview", dest="preview_video", action="store_false",
            help="skip the preview the worker renders after a job succeeds (video, plots, recording, export)",
        )  # fmt: skip
        g.add_argument(
            "--preview-close-up", dest="preview_close_up", action="store_true",
            help="add a close-up video to each job's preview (the camera follows the object, the fingers at it; a "
            "few seconds more per job)",
        )  # fmt: skip


def load_packed_hand(path: Path) -> HandDescription:
    """A packed hand description file (JSON), checked (``HandDescriptionError`` naming the field)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise HandDescriptionError([FieldProblem("hand", f"cannot read {path}: {exc}")]) from None
    return check_packed(parse_hand_description(data))


def job_options_from_args(args: argparse.Namespace) -> JobOptions:
    """The parsed flags as ``JobOptions``; out-of-range values raise ``InputError`` naming the option."""
    try:
        return JobOptions(
            seed=args.seed,
            keyframe_interval=args.keyframe_interval,
            max_generations=args.max_generations,
            popsize=args.popsize,
            loss_weights=args.weights,
            free_wrist_translation=args.free_wrist_translation,
            restarts=args.restarts,
            polish=getattr(args, "polish", True),
            tail=getattr(args, "tail", "full"),
            local_repair=getattr(args, "local_repair", False),
            evaluation_budget=getattr(args, "evaluation_budget", None),
            priority=getattr(args, "priority", 0),
            preview_video=getattr(args, "preview_video", True),
            preview_close_up=getattr(args, "preview_close_up", False),
            hand=load_packed_hand(args.hand_file) if getattr(args, "hand_file", None) else None,
        )
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'options'}: {e['msg']}" for e in exc.errors())
        raise InputError(f"invalid job options: {problems}") from None
