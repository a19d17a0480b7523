"""Parse a sequence NPZ (native format or DexYCB development file) from untrusted bytes (issue #16).

Every member is read through ``common.npz_safe.SafeNpz``: its dtype and shape are checked against what
the format says (``Spec`` below) and its frame count against ``max_frames`` *before* it is decompressed,
and floating members must be finite. Whatever is wrong becomes one ``SequenceValidationError`` naming the
member; no other exception leaves ``common.sequence_io.sequence_from_npz_bytes``, which dispatches between
this module's native reader and ``common.dexycb`` (the fuzz test in ``tests/unit/test_parser_fuzz.py`` holds
it to that).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np

from common.errors import SequenceValidationError
from common.npz_safe import NpzLimits, SafeNpz, Spec
from common.safe_text import shown
from common.sequence import MAX_NAME_CHARS, NUM_JOINTS, HandTrack, ManoParams, ObjectSpec, Sequence

FORMAT_NAME = "hoi-refine-sequence"
FORMAT_VERSION = 1
#: Hard ceiling on frames when the caller sets no ``max_frames`` (local files).
DEFAULT_MAX_FRAMES = 100_000

NUMBER = "iuf"
STRING = Spec("U", (), max_chars=MAX_NAME_CHARS)
SCALAR = Spec(NUMBER, ())
INTEGER = Spec("iu", ())
BOOLEAN = Spec("b", ())
META_JSON = Spec("U", (), max_chars=200_000)


@dataclass(frozen=True)
class ParseLimits:
    """What one sequence file may hold; the service builds it from its settings."""

    max_frames: int = DEFAULT_MAX_FRAMES
    max_mesh_vertices: int = 200_000
    max_mesh_faces: int = 400_000
    npz: NpzLimits = field(default_factory=NpzLimits)

    def dims(self) -> dict[str, int]:
        # T frames, V/F mesh vertices/faces, S hand sides, P MANO pose coefficients, B betas, N primitive sizes.
        return {"T": self.max_frames, "V": self.max_mesh_vertices, "F": self.max_mesh_faces,
                "S": 2, "P": 45, "B": 300, "N": 3}  # fmt: skip


def open_npz(blob: bytes, limits: ParseLimits) -> SafeNpz:
    return SafeNpz(blob, limits.npz, limits.dims())


def get_str(npz: SafeNpz, key: str, spec: Spec = STRING) -> str:
    return str(npz.get(key, spec)[()])


def get_float(npz: SafeNpz, key: str) -> float:
    return float(npz.get(key, SCALAR)[()])


def get_floats(npz: SafeNpz, key: str, dims: tuple[int | str, ...]) -> np.ndarray:
    return np.asarray(npz.get(key, Spec(NUMBER, dims)), dtype=np.float64)


def get_int(npz: SafeNpz, key: str, low: int, high: int) -> int:
    value = int(npz.get(key, INTEGER)[()])
    if not low <= value <= high:
        raise SequenceValidationError.single(key, f"must be in [{low}, {high}], got {value}")
    return value


def native_sequence(npz: SafeNpz) -> Sequence:
    """The native format's members as a ``Sequence`` (not yet validated: the caller validates)."""
    fmt = get_str(npz, "format")
    if fmt != FORMAT_NAME:
        raise SequenceValidationError.single("format", f"expected {FORMAT_NAME!r}, got {shown(fmt)}")
    version = get_int(npz, "format_version", 0, 2**31 - 1)
    if version != FORMAT_VERSION:
        raise SequenceValidationError.single(
            "format_version", f"unsupported version {version} (this build reads {FORMAT_VERSION})"
        )
    obj = ObjectSpec(
        name=get_str(npz, "object_name"),
        mass_kg=get_float(npz, "object_mass_kg"),
        friction=get_float(npz, "object_friction") if "object_friction" in npz else None,
    )
    if "object_primitive" in npz:
        obj.primitive = cast(Any, get_str(npz, "object_primitive"))
        obj.size = get_floats(npz, "object_size", ("N",))
    else:
        obj.mesh_vertices = get_floats(npz, "object_mesh_vertices", ("V", 3))
        obj.mesh_faces = np.asarray(npz.get("object_mesh_faces", Spec("iu", ("F", 3))), dtype=np.int64)
    hands = [_hand(npz, side) for side in _sides(npz)]
    meta = _meta(npz)
    return Sequence(
        name=get_str(npz, "name"),
        fps=get_float(npz, "fps"),
        frame_start=get_int(npz, "frame_start", 0, 2**31 - 1) if "frame_start" in npz else 0,
        object=obj,
        object_pose=get_floats(npz, "object_pose", ("T", 7)),
        hands=hands,
        world_from_source=get_floats(npz, "world_from_camera", (4, 4)) if "world_from_camera" in npz else None,
        up=get_floats(npz, "up", (3,)) if "up" in npz else None,
        meta=meta,
    )


def _sides(npz: SafeNpz) -> list[str]:
    sides = [str(s) for s in npz.get("hand_sides", Spec("U", ("S",), max_chars=5))]
    for side in sides:
        if side not in ("right", "left"):
            raise SequenceValidationError.single("hand_sides", f"entries must be 'right' or 'left', got {shown(side)}")
    if len(set(sides)) != len(sides):
        raise SequenceValidationError.single("hand_sides", f"each side may appear once, got {sides}")
    return sides


def _hand(npz: SafeNpz, side: str) -> HandTrack:
    hand = HandTrack(side=cast(Any, side), valid=npz.get(f"{side}_valid", Spec("b", ("T",))))
    if f"{side}_keypoints" in npz:
        hand.keypoints = get_floats(npz, f"{side}_keypoints", ("T", NUM_JOINTS, 3))
    if f"{side}_mano_hand_pose" in npz:
        fmt_key = f"{side}_mano_pose_format"
        pose_format = get_str(npz, fmt_key) if fmt_key in npz else "axis_angle"
        flat_key = f"{side}_mano_flat_hand_mean"
        hand.mano = ManoParams(
            global_orient=get_floats(npz, f"{side}_mano_global_orient", ("T", 3)),
            hand_pose=get_floats(npz, f"{side}_mano_hand_pose", ("T", "P")),
            trans=get_floats(npz, f"{side}_mano_trans", ("T", 3)),
            betas=get_floats(npz, f"{side}_mano_betas", ("B",)),
            pose_format=cast(Any, pose_format),
            flat_hand_mean=bool(npz.get(flat_key, BOOLEAN)[()]) if flat_key in npz else False,
        )
    return hand


def _meta(npz: SafeNpz) -> dict[str, str]:
    if "meta_json" not in npz:
        return {}
    text = get_str(npz, "meta_json", META_JSON)
    try:
        meta = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise SequenceValidationError.single("meta_json", "is not valid JSON") from exc
    if not isinstance(meta, dict) or not all(isinstance(v, str) for v in meta.values()):
        raise SequenceValidationError.single("meta_json", "must be a JSON object whose values are strings")
    return meta
