"""Sequence files: the native NPZ and JSON formats, mesh files, and format auto-detection.

Native NPZ (``format == "hoi-refine-sequence"``, ``format_version == 1``), keys:
  name, fps, frame_start, object_pose (T,7) [x y z qw qx qy qz],
  object_name, object_mass_kg, [object_friction],
  object_primitive + object_size | object_mesh_vertices (V,3) + object_mesh_faces (F,3),
  [world_from_camera (4,4) | up (3,)],
  hand_sides (list of 'right'/'left'), and per side S:
  S_valid (T,), [S_keypoints (T,21,3)],
  [S_mano_global_orient (T,3), S_mano_hand_pose (T,45|n), S_mano_trans (T,3), S_mano_betas (10,),
   S_mano_pose_format, S_mano_flat_hand_mean].
Version 2 (an articulated object, ``common.articulation``) adds object_base_part, and per jointed part k (J of them)
  object_part_names (J,), object_part_mass_kg (J,), object_part{k}_mesh_vertices + _mesh_faces | object_part{k}_
  primitive + _size, object_joint_names / _types ('revolute'|'prismatic') / _parents (J,), object_joint_axes (J,3),
  object_joint_origin_pos (J,3), object_joint_origin_quat (J,4) wxyz, object_joint_limits (J,2),
  [object_joint_damping (J,), object_joint_friction (J,)], object_articulation (T,J) joint values per frame.
Native JSON: the same content nested, see ``sequence_to_json_dict``; ``object.mesh_file`` (and a part's
``mesh_file``) may name an OBJ/PLY/STL/GLB file relative to the JSON file instead of inline ``mesh``.
The DexYCB development NPZs in ``shared/data/dexycb`` are read by ``common.dexycb``.

Reading is done for untrusted bytes: NPZ through ``common.sequence_npz`` (headers checked before anything is
decompressed), JSON through ``parse_json_text`` + ``sequence_from_json_dict`` (every value type-checked);
both end in ``Sequence.validate`` (at least ``MIN_FRAMES`` = 2 frames, finite bounded numbers, safe names).
Every problem is a ``SequenceValidationError`` naming its field.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import numpy as np

from common.articulation import MAX_PARTS, ObjectJoint
from common.dexycb import sequence_from_dexycb_npz
from common.dexycb_native import is_dexycb_sequence_dir, load_dexycb_native
from common.errors import FieldProblem, SequenceValidationError, UnsupportedFormatError
from common.mesh_io import load_mesh_file
from common.npz_writer import deterministic_npz_bytes
from common.safe_text import shown
from common.sequence import (
    PRIMITIVE_SIZE_LEN,
    HandTrack,
    ManoParams,
    ObjectPart,
    ObjectSpec,
    Sequence,
)
from common.sequence_npz import (
    ARTICULATED_FORMAT_VERSION,
    FORMAT_NAME,
    FORMAT_VERSION,
    READABLE_VERSIONS,
    ParseLimits,
    articulated_arrays,
    native_sequence,
    open_npz,
    shape_arrays,
)

# ---------------------------------------------------------------------- NPZ


def sequence_to_npz_bytes(seq: Sequence) -> bytes:
    """Serialise to the native NPZ format (compressed, deterministic: ``common.npz_writer``)."""
    arrays: dict[str, Any] = {
        "format": np.array(FORMAT_NAME),
        "format_version": np.array(ARTICULATED_FORMAT_VERSION if seq.object.parts else FORMAT_VERSION),
        "name": np.array(seq.name),
        "fps": np.array(float(seq.fps)),
        "frame_start": np.array(int(seq.frame_start)),
        "object_pose": seq.object_pose,
        "object_name": np.array(seq.object.name),
        "object_mass_kg": np.array(float(seq.object.mass_kg)),
        "hand_sides": np.array([h.side for h in seq.hands]),
        "meta_json": np.array(json.dumps(seq.meta)),
    }
    obj = seq.object
    if obj.friction is not None:
        arrays["object_friction"] = np.array(float(obj.friction))
    arrays.update(shape_arrays(obj, "object"))
    if obj.parts:
        arrays.update(articulated_arrays(seq))
    if seq.world_from_source is not None:
        arrays["world_from_camera"] = seq.world_from_source
    elif seq.up is not None:
        arrays["up"] = seq.up
    for hand in seq.hands:
        s = hand.side
        arrays[f"{s}_valid"] = hand.valid
        if hand.keypoints is not None:
            arrays[f"{s}_keypoints"] = hand.keypoints
        if hand.mano is not None:
            m = hand.mano
            arrays[f"{s}_mano_global_orient"] = m.global_orient
            arrays[f"{s}_mano_hand_pose"] = m.hand_pose
            arrays[f"{s}_mano_trans"] = m.trans
            arrays[f"{s}_mano_betas"] = m.betas
            arrays[f"{s}_mano_pose_format"] = np.array(m.pose_format)
            arrays[f"{s}_mano_flat_hand_mean"] = np.array(bool(m.flat_hand_mean))
    # Fixed zip timestamps and member order: the bytes are embedded in refinement results (``sequence_npz``),
    # which must be identical between runs.
    return deterministic_npz_bytes(arrays)


def sequence_from_npz_bytes(
    blob: bytes, max_frames: int | None = None, source_path: Path | None = None, limits: ParseLimits | None = None
) -> Sequence:
    """Parse the native NPZ format (or the DexYCB development NPZ) from untrusted bytes and validate.

    ``source_path`` (when the bytes came from a file) lets DexYCB files find the YCB folder beside them;
    ``limits`` (frames, mesh size, uncompressed bytes) default to ``ParseLimits()``, ``max_frames`` overrides
    its frame limit. Every member is checked before it is decompressed (``common.sequence_npz``).
    """
    limits = limits or ParseLimits()
    if max_frames is not None:
        limits = replace(limits, max_frames=max_frames)
    with open_npz(blob, limits) as npz:
        if "hand_joints" in npz and "object_name" in npz and "format" not in npz:
            return sequence_from_dexycb_npz(npz, max_frames=limits.max_frames, path=source_path)
        seq = native_sequence(npz)
    return seq.validate(max_frames=limits.max_frames)


# ---------------------------------------------------------------------- JSON


def sequence_to_json_dict(seq: Sequence) -> dict[str, Any]:
    """The native JSON form (mesh inline), suitable for ``POST /v1/jobs``."""
    obj = seq.object
    obj_d = _shape_json(obj)
    if obj.friction is not None:
        obj_d["friction"] = obj.friction
    if obj.parts:
        obj_d["base_part"] = obj.base_part
        obj_d["parts"] = [{**_shape_json(p.shape), "joint": _joint_json(p.joint)} for p in obj.parts]
    hands = []
    for h in seq.hands:
        hd: dict[str, Any] = {"side": h.side, "valid": h.valid.tolist()}
        if h.keypoints is not None:
            hd["keypoints"] = h.keypoints.tolist()
        if h.mano is not None:
            m = h.mano
            hd["mano"] = {
                "global_orient": m.global_orient.tolist(),
                "hand_pose": m.hand_pose.tolist(),
                "trans": m.trans.tolist(),
                "betas": m.betas.tolist(),
                "pose_format": m.pose_format,
                "flat_hand_mean": m.flat_hand_mean,
            }
        hands.append(hd)
    out: dict[str, Any] = {
        "format": FORMAT_NAME,
        "format_version": ARTICULATED_FORMAT_VERSION if obj.parts else FORMAT_VERSION,
        "name": seq.name,
        "fps": seq.fps,
        "frame_start": seq.frame_start,
        "object": obj_d,
        "object_pose": seq.object_pose.tolist(),
        "hands": hands,
        "meta": seq.meta,
    }
    if seq.world_from_source is not None:
        out["world_from_camera"] = seq.world_from_source.tolist()
    elif seq.up is not None:
        out["up"] = seq.up.tolist()
    if seq.articulation is not None:
        out["articulation"] = seq.articulation.tolist()
    return out


def _shape_json(obj: ObjectSpec) -> dict[str, Any]:
    out: dict[str, Any] = {"name": obj.name, "mass_kg": obj.mass_kg}
    if obj.primitive is not None:
        assert obj.size is not None
        out["primitive"] = {"kind": obj.primitive, "size": obj.size.tolist()}
    else:
        assert obj.mesh_vertices is not None and obj.mesh_faces is not None
        out["mesh"] = {"vertices": obj.mesh_vertices.tolist(), "faces": obj.mesh_faces.tolist()}
    return out


def _joint_json(joint: ObjectJoint) -> dict[str, Any]:
    out: dict[str, Any] = {
        "name": joint.name, "type": joint.kind, "parent": joint.parent, "axis": np.asarray(joint.axis).tolist(),
        "origin": {"pos": np.asarray(joint.origin_pos).tolist(), "quat": np.asarray(joint.origin_quat).tolist()},
        "limits": np.asarray(joint.limits).tolist(),
    }  # fmt: skip
    for key in ("damping", "friction"):
        if getattr(joint, key) is not None:
            out[key] = getattr(joint, key)
    return out


def sequence_from_json_dict(
    doc: Any, base_dir: Path | None = None, max_frames: int | None = None
) -> Sequence:
    """Parse the native JSON form and validate. ``base_dir`` resolves ``object.mesh_file``.

    ``doc`` may be anything ``json.loads`` returns: every value is type-checked before use, and every
    problem found is reported in one ``SequenceValidationError``.
    """
    problems: list[FieldProblem] = []

    def need(d: Any, key: str, path: str) -> Any:
        if not isinstance(d, dict) or key not in d:
            problems.append(FieldProblem(path, "is required"))
            return None
        return d[key]

    def arr(value: Any, path: str, dtype: Any = np.float64) -> Any:
        if value is None:
            return None
        if not isinstance(value, list) or any(isinstance(v, (str, dict)) for v in _flat_head(value)):
            problems.append(FieldProblem(path, "must be a (nested) list of numbers of a regular shape"))
            return None
        try:
            out = np.asarray(value, dtype=dtype)
        except (ValueError, TypeError, OverflowError, RecursionError):
            problems.append(FieldProblem(path, "must be a (nested) list of numbers of a regular shape"))
            return None
        if out.dtype.kind not in "biuf":
            problems.append(FieldProblem(path, "must be a (nested) list of numbers (or booleans) of a regular shape"))
            return None
        return out

    def num(value: Any, path: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            if value is not None:
                problems.append(FieldProblem(path, f"must be a number, got {type(value).__name__}"))
            return float("nan")
        try:
            return float(value)
        except OverflowError:
            problems.append(FieldProblem(path, "is out of range"))
            return float("nan")

    def text(value: Any, path: str, default: str) -> str:
        if value is None:
            return default
        if not isinstance(value, str):
            problems.append(FieldProblem(path, f"must be a string, got {type(value).__name__}"))
            return default
        return value

    if not isinstance(doc, dict):
        raise SequenceValidationError.single("body", "must be a JSON object")
    if doc.get("format", FORMAT_NAME) != FORMAT_NAME:
        raise SequenceValidationError.single("format", f"expected {FORMAT_NAME!r}")
    version = doc.get("format_version", FORMAT_VERSION)
    if isinstance(version, bool) or version not in READABLE_VERSIONS:
        raise SequenceValidationError.single(
            "format_version", f"this build reads versions {', '.join(map(str, READABLE_VERSIONS))}"
        )

    od = need(doc, "object", "object")
    if od is not None and not isinstance(od, dict):
        problems.append(FieldProblem("object", "must be an object"))
    od = od if isinstance(od, dict) else {}

    def shape(d: dict[str, Any], f: str) -> ObjectSpec:
        out = ObjectSpec(
            name=text(d.get("name"), f"{f}.name", "object"),
            mass_kg=num(need(d, "mass_kg", f"{f}.mass_kg"), f"{f}.mass_kg"),
            friction=None if d.get("friction") is None else num(d["friction"], f"{f}.friction"),
        )
        if "primitive" in d:
            prim = d["primitive"]
            kind = prim.get("kind") if isinstance(prim, dict) else None
            if not isinstance(kind, str) or kind not in PRIMITIVE_SIZE_LEN:
                problems.append(FieldProblem(f"{f}.primitive.kind", f"must be one of {sorted(PRIMITIVE_SIZE_LEN)}"))
            else:
                out.primitive = cast(Any, kind)
                out.size = arr(need(prim, "size", f"{f}.primitive.size"), f"{f}.primitive.size")
        if "mesh" in d:
            mesh = d["mesh"] if isinstance(d["mesh"], dict) else {}
            out.mesh_vertices = arr(need(mesh, "vertices", f"{f}.mesh.vertices"), f"{f}.mesh.vertices")
            out.mesh_faces = arr(need(mesh, "faces", f"{f}.mesh.faces"), f"{f}.mesh.faces", np.int64)
        if "mesh_file" in d:
            if not isinstance(d["mesh_file"], str):
                problems.append(FieldProblem(f"{f}.mesh_file", "must be a path (string)"))
            else:
                mesh_path = Path(d["mesh_file"])
                if not mesh_path.is_absolute() and base_dir is not None:
                    mesh_path = base_dir / mesh_path
                out.mesh_vertices, out.mesh_faces = load_mesh_file(mesh_path)
        return out

    def joint(d: Any, f: str) -> ObjectJoint:
        if not isinstance(d, dict):
            problems.append(FieldProblem(f, "must be an object (name, type, parent, axis, origin, limits)"))
            d = {}
        origin = d.get("origin", {})
        if not isinstance(origin, dict):
            problems.append(FieldProblem(f"{f}.origin", "must be an object {pos, quat}"))
            origin = {}
        return ObjectJoint(
            name=text(need(d, "name", f"{f}.name"), f"{f}.name", ""),
            kind=cast(Any, text(need(d, "type", f"{f}.type"), f"{f}.type", "")),
            parent=text(need(d, "parent", f"{f}.parent"), f"{f}.parent", ""),
            axis=arr(need(d, "axis", f"{f}.axis"), f"{f}.axis"),
            origin_pos=arr(origin.get("pos", [0.0, 0.0, 0.0]), f"{f}.origin.pos"),
            origin_quat=arr(origin.get("quat", [1.0, 0.0, 0.0, 0.0]), f"{f}.origin.quat"),
            limits=arr(need(d, "limits", f"{f}.limits"), f"{f}.limits"),
            damping=None if d.get("damping") is None else num(d["damping"], f"{f}.damping"),
            friction=None if d.get("friction") is None else num(d["friction"], f"{f}.friction"),
        )

    obj = shape(od, "object")
    if "base_part" in od:
        obj.base_part = text(od["base_part"], "object.base_part", "base")
    part_docs = od.get("parts", [])
    if not isinstance(part_docs, list):
        problems.append(FieldProblem("object.parts", "must be a list"))
        part_docs = []
    for k, pd in enumerate(part_docs[: MAX_PARTS + 1]):  # one more than allowed is enough to say so
        f = f"object.parts[{k}]"
        if not isinstance(pd, dict):
            problems.append(FieldProblem(f, "must be an object (name, mass_kg, mesh or primitive, joint)"))
            continue
        obj.parts.append(ObjectPart(shape(pd, f), joint(need(pd, "joint", f"{f}.joint"), f"{f}.joint")))

    hands = []
    hand_docs = need(doc, "hands", "hands")
    if hand_docs is not None and not isinstance(hand_docs, list):
        problems.append(FieldProblem("hands", "must be a list"))
        hand_docs = []
    for i, hd in enumerate((hand_docs or [])[:3]):  # more than two is an error; three are enough to say so
        p = f"hands[{i}]"
        if not isinstance(hd, dict):
            problems.append(FieldProblem(p, "must be an object"))
            continue
        valid = arr(need(hd, "valid", f"{p}.valid"), f"{p}.valid", None)
        if valid is not None and valid.dtype != np.bool_:
            problems.append(FieldProblem(f"{p}.valid", "must be a list of booleans"))
        side = hd.get("side")
        if not isinstance(side, str):
            problems.append(FieldProblem(f"{p}.side", "must be 'right' or 'left'"))
        hand = HandTrack(
            side=cast(Any, side),  # the value is validated in Sequence.validate
            valid=valid if valid is not None else np.zeros(0, dtype=bool),
            keypoints=arr(hd.get("keypoints"), f"{p}.keypoints"),
        )
        md = hd.get("mano")
        if md is not None and not isinstance(md, dict):
            problems.append(FieldProblem(f"{p}.mano", "must be an object"))
        if isinstance(md, dict):
            flat = md.get("flat_hand_mean", False)
            if not isinstance(flat, bool):
                problems.append(FieldProblem(f"{p}.mano.flat_hand_mean", "must be true or false"))
            hand.mano = ManoParams(
                global_orient=arr(need(md, "global_orient", f"{p}.mano.global_orient"), f"{p}.mano.global_orient"),
                hand_pose=arr(need(md, "hand_pose", f"{p}.mano.hand_pose"), f"{p}.mano.hand_pose"),
                trans=arr(need(md, "trans", f"{p}.mano.trans"), f"{p}.mano.trans"),
                betas=arr(md.get("betas", [0.0] * 10), f"{p}.mano.betas"),
                pose_format=cast(Any, text(md.get("pose_format"), f"{p}.mano.pose_format", "axis_angle")),
                flat_hand_mean=bool(flat),
            )
        hands.append(hand)

    fps = num(need(doc, "fps", "fps"), "fps")
    pose = arr(need(doc, "object_pose", "object_pose"), "object_pose")
    frame_start = doc.get("frame_start", 0)
    if not isinstance(frame_start, int) or isinstance(frame_start, bool):
        problems.append(FieldProblem("frame_start", "must be an integer"))
        frame_start = 0
    world = arr(doc.get("world_from_camera"), "world_from_camera")
    up = arr(doc.get("up"), "up")
    meta = doc.get("meta") or {}
    if not isinstance(meta, dict) or not all(isinstance(v, str) for v in meta.values()):
        problems.append(FieldProblem("meta", "must be an object whose values are strings"))
        meta = {}
    name = text(doc.get("name"), "name", "sequence")
    articulation = arr(doc.get("articulation"), "articulation")
    if problems:
        raise SequenceValidationError(problems)
    seq = Sequence(
        name=name, fps=fps, frame_start=frame_start, object=obj, object_pose=pose, hands=hands,
        world_from_source=world, up=up, meta=dict(meta), articulation=articulation,
    )  # fmt: skip
    return seq.validate(max_frames=max_frames)


def parse_json_text(blob: bytes | str, field: str = "sequence") -> Any:
    """``json.loads`` for untrusted text: NaN/Infinity literals, too-deep nesting, oversized integers and
    bad UTF-8 become a ``SequenceValidationError`` naming ``field``."""

    def no_constants(name: str) -> Any:
        raise ValueError(f"{name} is not valid JSON (numbers must be finite)")

    try:
        return json.loads(blob, parse_constant=no_constants)
    except RecursionError as exc:
        raise SequenceValidationError.single(field, "is nested too deeply") from exc
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
        reason = exc.args[0] if isinstance(exc, ValueError) and exc.args else "not UTF-8"
        raise SequenceValidationError.single(field, f"is not valid JSON: {shown(str(reason), 120)}") from exc


def sequence_from_json_bytes(
    blob: bytes, base_dir: Path | None = None, max_frames: int | None = None
) -> Sequence:
    """Parse native JSON text and validate (every problem a ``SequenceValidationError``)."""
    return sequence_from_json_dict(parse_json_text(blob), base_dir=base_dir, max_frames=max_frames)


def _flat_head(value: list[Any], depth: int = 0) -> list[Any]:
    """The first element at each nesting level (a cheap look for strings or objects inside a number list)."""
    out: list[Any] = []
    while isinstance(value, list) and value and depth < 8:
        value = value[0]
        out.append(value)
        depth += 1
    return out

# ---------------------------------------------------------------------- files


def load_sequence(path: Path | str, max_frames: int | None = None, object_dir: Path | None = None) -> Sequence:
    """Read a sequence file, choosing the format by suffix (``.npz`` or ``.json``; ``.npy``: an ARCTIC recording,
    ``common.arctic``, whose object folder ``object_dir`` overrides the one its layout implies), or a DexYCB
    sequence folder."""
    path = Path(path)
    if path.is_dir() or path.name == "meta.yml":
        # DexYCB native layout: <root>/<subject>/<sequence>/{meta.yml,pose.npz}
        seq_dir = path if path.is_dir() else path.parent
        if is_dexycb_sequence_dir(seq_dir):
            return load_dexycb_native(seq_dir, max_frames=max_frames)
    if not path.is_file():
        raise UnsupportedFormatError(f"{path} is not a file (nor a DexYCB sequence folder with meta.yml + pose.npz)")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        seq = sequence_from_npz_bytes(path.read_bytes(), max_frames=max_frames, source_path=path)
        if "source_path" not in seq.meta:
            seq.meta["source_path"] = str(path)
        return seq
    if suffix == ".json":
        return sequence_from_json_bytes(path.read_bytes(), base_dir=path.parent, max_frames=max_frames)
    if suffix == ".npy":
        from common.arctic import load_arctic

        return load_arctic(path, object_dir=object_dir, max_frames=max_frames)
    raise UnsupportedFormatError(
        f"{path.name}: unknown sequence format {suffix!r} (expected .npz, .json or an ARCTIC .npy)"
    )


def save_sequence(seq: Sequence, path: Path | str) -> None:
    path = Path(path)
    if path.suffix.lower() == ".json":
        path.write_text(json.dumps(sequence_to_json_dict(seq)))
    else:
        path.write_bytes(sequence_to_npz_bytes(seq))
