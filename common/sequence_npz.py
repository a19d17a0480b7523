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

from common.articulation import MAX_PARTS, ObjectJoint
from common.errors import SequenceValidationError
from common.npz_safe import NpzLimits, SafeNpz, Spec
from common.safe_text import shown
from common.sequence import MAX_NAME_CHARS, NUM_JOINTS, HandTrack, ManoParams, ObjectPart, ObjectSpec, Sequence

FORMAT_NAME = "hoi-refine-sequence"
#: Version 1: a rigid object. Version 2 adds an articulated object's parts, joints and ``object_articulation``;
#: rigid sequences are still written as version 1, so their bytes (embedded in results) stay as they were.
FORMAT_VERSION = 1
ARTICULATED_FORMAT_VERSION = 2
READABLE_VERSIONS = (FORMAT_VERSION, ARTICULATED_FORMAT_VERSION)
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
        # J: an articulated object's jointed parts.
        return {"T": self.max_frames, "V": self.max_mesh_vertices, "F": self.max_mesh_faces,
                "S": 2, "P": 45, "B": 300, "N": 3, "J": MAX_PARTS}  # fmt: skip


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
    if version not in READABLE_VERSIONS:
        raise SequenceValidationError.single(
            "format_version",
            f"unsupported version {version} (this build reads {', '.join(map(str, READABLE_VERSIONS))})",
        )
    obj = ObjectSpec(
        name=get_str(npz, "object_name"),
        mass_kg=get_float(npz, "object_mass_kg"),
        friction=get_float(npz, "object_friction") if "object_friction" in npz else None,
    )
    _shape(npz, obj, "object")
    articulation = None
    if version == ARTICULATED_FORMAT_VERSION:
        obj.base_part = get_str(npz, "object_base_part")
        obj.parts = _parts(npz)
        articulation = get_floats(npz, "object_articulation", ("T", len(obj.parts)))
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
        articulation=articulation,
    )


def _shape(npz: SafeNpz, obj: ObjectSpec, prefix: str) -> None:
    """A mesh (``{prefix}_mesh_vertices`` + ``_faces``) or a primitive (``{prefix}_primitive`` + ``_size``)."""
    if f"{prefix}_primitive" in npz:
        obj.primitive = cast(Any, get_str(npz, f"{prefix}_primitive"))
        obj.size = get_floats(npz, f"{prefix}_size", ("N",))
    else:
        obj.mesh_vertices = get_floats(npz, f"{prefix}_mesh_vertices", ("V", 3))
        obj.mesh_faces = np.asarray(npz.get(f"{prefix}_mesh_faces", Spec("iu", ("F", 3))), dtype=np.int64)


#: Per-joint members of version 2 (J rows each); damping and friction are optional (all or none).
JOINT_KEYS = ("object_joint_names", "object_joint_types", "object_joint_parents", "object_joint_axes",
              "object_joint_origin_pos", "object_joint_origin_quat", "object_joint_limits")


def _parts(npz: SafeNpz) -> list[ObjectPart]:
    names = [str(v) for v in npz.get("object_part_names", Spec("U", ("J",), max_chars=MAX_NAME_CHARS))]
    n = len(names)
    masses = get_floats(npz, "object_part_mass_kg", (n,))
    text = Spec("U", (n,), max_chars=MAX_NAME_CHARS)
    joint_names = [str(v) for v in npz.get("object_joint_names", text)]
    kinds = [str(v) for v in npz.get("object_joint_types", text)]
    parents = [str(v) for v in npz.get("object_joint_parents", text)]
    axes = get_floats(npz, "object_joint_axes", (n, 3))
    origin_pos = get_floats(npz, "object_joint_origin_pos", (n, 3))
    origin_quat = get_floats(npz, "object_joint_origin_quat", (n, 4))
    limits = get_floats(npz, "object_joint_limits", (n, 2))
    damping = get_floats(npz, "object_joint_damping", (n,)) if "object_joint_damping" in npz else None
    friction = get_floats(npz, "object_joint_friction", (n,)) if "object_joint_friction" in npz else None
    parts = []
    for k in range(n):
        shape = ObjectSpec(name=names[k], mass_kg=float(masses[k]))
        _shape(npz, shape, f"object_part{k}")
        joint = ObjectJoint(
            name=joint_names[k], kind=cast(Any, kinds[k]), parent=parents[k], axis=axes[k], origin_pos=origin_pos[k],
            origin_quat=origin_quat[k], limits=limits[k],
            damping=None if damping is None else float(damping[k]),
            friction=None if friction is None else float(friction[k]),
        )  # fmt: skip
        parts.append(ObjectPart(shape, joint))
    return parts


def articulated_arrays(seq: Sequence) -> dict[str, Any]:
    """The version-2 members of an articulated sequence (``common.sequence_io.sequence_to_npz_bytes``)."""
    obj = seq.object
    joints = obj.joints
    out: dict[str, Any] = {
        "object_base_part": np.array(obj.base_part),
        "object_part_names": np.array([p.shape.name for p in obj.parts]),
        "object_part_mass_kg": np.array([float(p.shape.mass_kg) for p in obj.parts]),
        "object_joint_names": np.array([j.name for j in joints]),
        "object_joint_types": np.array([j.kind for j in joints]),
        "object_joint_parents": np.array([j.parent for j in joints]),
        "object_joint_axes": np.array([j.axis for j in joints], dtype=np.float64),
        "object_joint_origin_pos": np.array([j.origin_pos for j in joints], dtype=np.float64),
        "object_joint_origin_quat": np.array([j.origin_quat for j in joints], dtype=np.float64),
        "object_joint_limits": np.array([j.limits for j in joints], dtype=np.float64),
        "object_articulation": np.asarray(seq.articulation, dtype=np.float64),
    }
    if all(j.damping is not None for j in joints):
        out["object_joint_damping"] = np.array([j.damping for j in joints], dtype=np.float64)
    if all(j.friction is not None for j in joints):
        out["object_joint_friction"] = np.array([j.friction for j in joints], dtype=np.float64)
    for k, part in enumerate(obj.parts):
        out.update(shape_arrays(part.shape, f"object_part{k}"))
    return out


def shape_arrays(obj: ObjectSpec, prefix: str) -> dict[str, Any]:
    """A shape's members: ``{prefix}_primitive`` + ``_size`` or ``{prefix}_mesh_vertices`` + ``_faces``."""
    if obj.primitive is not None:
        return {f"{prefix}_primitive": np.array(obj.primitive), f"{prefix}_size": obj.size}
    return {f"{prefix}_mesh_vertices": obj.mesh_vertices, f"{prefix}_mesh_faces": obj.mesh_faces}


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
