"""``hoi-refine replay SEQ --out RESULT.npz``: the raw replay (the hand driven along its retargeted reference, no
optimisation; the object moves only through contact) with its metrics table. ``--hand`` / ``--robot-dir`` as for
``refine``: a robot hand driven along the recorded hand retargeted to it (issue #55)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from worker.commands.inspect import add_object_dir_argument
from worker.commands.refine import add_hand_arguments


def register(subparsers: Any) -> None:
    r = subparsers.add_parser(
        "replay",
        help="raw replay: drive the hand along the retargeted reference (no optimisation) and report metrics",
        description="Retarget the hand, simulate the object from its rest pose, write trajectory + contacts.",
    )
    src = r.add_mutually_exclusive_group(required=True)
    src.add_argument("sequence", type=Path, nargs="?", help="sequence file (as for inspect)")
    src.add_argument("--example", action="store_true", help="use the built-in synthetic grasp-and-lift")
    r.add_argument("--out", type=Path, default=None, help="result file to write (.npz)")
    add_object_dir_argument(r)
    add_hand_arguments(r)
    r.set_defaults(func=cmd_replay)


def run_replay(seq: Any, out: Path | None, hand: Any = None) -> Any:
    """The raw replay of ``seq`` printed (and written to ``out``); ``hand``: a packed robot hand description."""
    from rich.console import Console

    from common.metrics_table import metrics_table
    from common.settings import get_settings
    from worker.simulation.replay import raw_replay, replay_result_bytes

    console = Console()
    with console.status(f"raw replay of {seq.name} ({seq.num_frames} frames)..."):
        settings = get_settings()
        result = raw_replay(seq, cache_dir=settings.resolved_cache_dir(), mano_dir=settings.mano_dir, hand=hand)
    paper = result.metrics.get("paper") or {}
    if "success" in paper:  # the raw replay's own outcome; a refinement's result says why (``refine``)
        verdict = "executable" if paper["success"] else "NOT executable"
        console.print(f"outcome (raw replay, not refined): {verdict} (the paper's protocol: every frame from 10 on "
                      "within 3 cm / 30 deg)", highlight=False)
    console.print(metrics_table({"raw": result.metrics}, title=f"raw replay: {seq.name}"))
    t = result.timings
    ik = ", ".join(f"{side} {v:.2f} mm" for side, v in result.ik_residual_mm().items())
    console.print(
        f"IK residual (mean over valid frames): {ik}; {result.steps} simulated steps; "
        f"retarget {t['retarget_s']:.2f} s, scene {t['build_scene_s']:.2f} s, simulate {t['simulate_s']:.2f} s "
        f"({t['steps_per_second']:.0f} steps/s); {len(result.contacts['contact_frame'])} contacts recorded"
    )
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(replay_result_bytes(result))
        console.print(f"wrote {out}")
    return result


def cmd_replay(args: argparse.Namespace) -> int:
    from common.sequence_io import load_sequence
    from common.settings import get_settings
    from worker.robot import resolve_hand

    # Before loading, as ``refine`` does: a bad hand should not wait for a slow load.
    hand = resolve_hand(args.hand, args.robot_dir or get_settings().robot_dir)
    if args.example:
        from worker.example.sequences import example_sequence

        seq = example_sequence()
    else:
        seq = load_sequence(args.sequence, max_frames=get_settings().max_frames, object_dir=args.object_dir)
    run_replay(seq, args.out, hand)
    return 0
