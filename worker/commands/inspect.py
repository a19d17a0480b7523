"""``hoi-refine inspect SEQ``: what a sequence file holds and whether it validates (exit 2 with the field-named
message when it does not), and whether its MANO-only hands can run here."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "inspect", help="show what a sequence file holds and whether it is valid", description=__doc__
    )
    p.add_argument("sequence", type=Path, help="sequence file (.npz native or DexYCB, .json, DexYCB folder)")
    p.set_defaults(func=cmd_inspect)


def _describe(seq: Any) -> list[tuple[str, str]]:
    obj = seq.object
    shape = (
        f"{obj.primitive} {[round(float(s), 4) for s in obj.size]}"
        if obj.primitive
        else f"mesh, {len(obj.mesh_vertices)} vertices, {len(obj.mesh_faces)} faces"
    )
    rows = [
        ("name", seq.name),
        ("frames", f"{seq.num_frames} at {seq.fps:g} fps ({seq.num_frames / seq.fps:.2f} s), first {seq.frame_start}"),
        ("object", f"{obj.name}: {shape}, {obj.mass_kg:g} kg"),
        ("world frame", "world_from_camera given" if seq.world_from_source is not None else "from up vector / default"),
    ]
    for h in seq.hands:
        parts = [f"{int(h.valid.sum())}/{len(h.valid)} valid frames"]
        if h.keypoints is not None:
            parts.append("21 keypoints")
        if h.mano is not None:
            parts.append(f"MANO ({h.mano.pose_format}, {h.mano.hand_pose.shape[1]} pose values)")
        rows.append((f"{h.side} hand", ", ".join(parts)))
    pose = seq.object_pose_world()
    lift = 100 * (pose[:, 2].max() - pose[0, 2])
    rows.append(("object lift", f"{lift:.1f} cm above its frame-0 height at most"))
    for key, value in sorted(seq.meta.items()):
        rows.append((f"meta.{key}", value))
    return rows


def cmd_inspect(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from common.errors import SequenceValidationError
    from common.sequence_io import load_sequence
    from common.settings import get_settings

    console = Console()
    try:
        seq = load_sequence(args.sequence, max_frames=get_settings().max_frames)
    except SequenceValidationError as exc:
        console.print(f"[bold red]invalid[/] {args.sequence}")
        for problem in exc.problems:
            console.print(f"  {problem}")
        raise
    table = Table(title=str(args.sequence), show_header=False)
    for key, value in _describe(seq):
        table.add_row(key, value)
    console.print(table)
    _check_mano(seq, console)
    console.print("[bold green]valid[/]: every field passed validation")
    return 0


def _check_mano(seq: Any, console: Any) -> None:
    """MANO-only hands cannot run without the model files: say so, then raise the error that names
    ``HOI_REFINE_MANO_DIR`` (``common.cli.main`` prints it and exits 2). No torch is imported."""
    from common.errors import ManoModelMissingError
    from common.settings import get_settings
    from worker.hand.mano import mano_available, require_mano_models

    try:
        require_mano_models(seq, get_settings().mano_dir)
    except ManoModelMissingError:
        console.print("[bold red]cannot run[/]: a hand is given only as MANO parameters and the MANO model is missing")
        raise
    sides = [h.side for h in seq.hands if h.mano is not None]
    if sides and mano_available(sides, get_settings().mano_dir):
        console.print(f"MANO model found for the {' and '.join(sides)} hand: the MANO hand is used")
