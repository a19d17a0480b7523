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
    p.add_argument("sequence", type=Path, help="sequence file (.npz native or DexYCB, .json, DexYCB folder, ARCTIC "
                   ".npy)")
    add_object_dir_argument(p)
    p.set_defaults(func=cmd_inspect)


def add_object_dir_argument(p: Any) -> None:
    """``--object-dir``, shared by ``inspect``, ``replay`` and ``refine``."""
    p.add_argument("--object-dir", type=Path, default=None, metavar="DIR",
                   help="an ARCTIC recording's object folder (dexmachina-processed: the one holding <object>.urdf; "
                   "release: meta/object_vtemplates/<object>), when it is not where the layout puts it")


def _shape_text(obj: Any) -> str:
    shape = (
        f"{obj.primitive} {[round(float(s), 4) for s in obj.size]}"
        if obj.primitive
        else f"mesh, {len(obj.mesh_vertices)} vertices, {len(obj.mesh_faces)} faces"
    )
    return f"{shape}, {obj.mass_kg:g} kg"


def _joint_rows(seq: Any) -> list[tuple[str, str]]:
    """An articulated object's parts, joints and the recorded range of every joint."""
    obj = seq.object
    names = obj.part_names
    rows = [("parts", f"{len(names)}: {names[0]} (base), " + ", ".join(names[1:]))]
    for k, (part, joint) in enumerate(zip(obj.part_shapes()[1:], obj.joints, strict=True)):
        rows.append((f"part {part.name}", _shape_text(part)))
        scale, unit, si = joint.display_scale(), joint.unit, "rad" if joint.kind == "revolute" else "m"
        lo, hi = (float(v) for v in joint.limits)
        axis = " ".join(f"{float(v):.3g}" for v in joint.axis)
        origin = " ".join(f"{float(v):.4g}" for v in joint.origin_pos)
        rows.append((f"joint {joint.name}", f"{joint.kind}, {joint.parent} -> {part.name}, axis ({axis}), origin "
                     f"({origin}) m, limits [{lo:.4g}, {hi:.4g}] {si} ([{lo * scale:.1f}, {hi * scale:.1f}] {unit})"))
        values = seq.articulation[:, k]
        a, b = float(values.min()), float(values.max())
        rows.append((f"articulation {joint.name}", f"recorded {a:.4g} to {b:.4g} {si} ({a * scale:.1f} to "
                     f"{b * scale:.1f} {unit}; frame 0: {float(values[0]) * scale:.1f} {unit})"))
    return rows


def _describe(seq: Any) -> list[tuple[str, str]]:
    obj = seq.object
    base = f" (base part {obj.base_part})" if obj.articulated else ""
    rows = [
        ("name", seq.name),
        ("frames", f"{seq.num_frames} at {seq.fps:g} fps ({seq.num_frames / seq.fps:.2f} s), first {seq.frame_start}"),
        ("object", f"{obj.name}{base}: {_shape_text(obj)}"),
    ]
    if obj.articulated:
        rows += _joint_rows(seq)
    rows.append(
        ("world frame", "world_from_camera given" if seq.world_from_source is not None else "from up vector / default")
    )
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
        seq = load_sequence(args.sequence, max_frames=get_settings().max_frames, object_dir=args.object_dir)
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
