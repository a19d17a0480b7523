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
Native JSON: the same content nested, see ``sequence_to_json_dict``; ``object.mesh_file`` may name an
OBJ/PLY/STL/GLB file relative to the JSON file instead of inline ``object.mesh``.
The DexYCB development NPZs in ``shared/data/dexycb`` are read by ``common.dexycb``.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any, cast

import numpy as np

from common.dexycb import sequence_from_dexycb_npz
from common.dexycb_native import is_dexycb_sequence_dir, load_dexycb_native
from common.errors import FieldProblem, SequenceValidationError, UnsupportedFormatError
from common.mesh_io import load_mesh_file
from common.npz_writer import deterministic_npz_bytes
from common.sequence import (
    PRIMITIVE_SIZE_LEN,
    HandTrack,
    ManoParams,
    ObjectSpec,
    Sequence,
)

FORMAT_NAME = "hoi-refine-sequence"
FORMAT_VERSION = 1


# ---------------------------------------------------------------------- NPZ


def sequence_to_npz_bytes(seq: Sequence) -> bytes:
    """Serialise to the native NPZ format (compressed, deterministic: ``common.npz_writer``)."""
    arrays: dict[str, Any] = {
        "format": np.array(FORMAT_NAME),
        "format_version": np.array(FORMAT_VERSION),
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
    if obj.primitive is not None:
        arrays["object_primitive"] = np.array(obj.primitive)
        arrays["object_size"] = obj.size
    else:
        arrays["object_mesh_vertices"] = obj.mesh_vertices
        arrays["object_mesh_faces"] = obj.mesh_faces
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


def _npz_get(data: Any, key: str, required: bool = True) -> Any:
    if key in data.files:
        return data[key]
    if required:
        raise SequenceValidationError.single(key, "is missing from the NPZ file")
    return None


def _as_float(x: Any) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def sequence_from_npz_bytes(
    blob: bytes, max_frames: int | None = None, source_path: Path | None = None
) -> Sequence:
    """Parse the native NPZ format (or the DexYCB development NPZ) and validate.

    ``source_path`` (when the bytes came from a file) lets DexYCB files find the YCB folder beside them.
    """
    try:
        data = np.load(io.BytesIO(blob), allow_pickle=False)
    except Exception as exc:
        raise UnsupportedFormatError(f"not a readable NPZ file: {exc}") from exc
    with data:
        if "hand_joints" in data.files and "object_name" in data.files and "format" not in data.files:
            return sequence_from_dexycb_npz(data, max_frames=max_frames, path=source_path)
        fmt = str(_npz_get(data, "format"))
        if fmt != FORMAT_NAME:
            raise SequenceValidationError.single("format", f"expected {FORMAT_NAME!r}, got {fmt!r}")
        version = int(_npz_get(data, "format_version"))
        if version != FORMAT_VERSION:
            raise SequenceValidationError.single(
                "format_version", f"unsupported version {version} (this build reads {FORMAT_VERSION})"
            )
        obj = ObjectSpec(
            name=str(_npz_get(data, "object_name")),
            mass_kg=float(_npz_get(data, "object_mass_kg")),
            friction=_opt_float(_npz_get(data, "object_friction", required=False)),
        )
        primitive = _npz_get(data, "object_primitive", required=False)
        if primitive is not None:
            obj.primitive = cast(Any, str(primitive))
            obj.size = _as_float(_npz_get(data, "object_size"))
        else:
            obj.mesh_vertices = _as_float(_npz_get(data, "object_mesh_vertices"))
            obj.mesh_faces = np.asarray(_npz_get(data, "object_mesh_faces"), dtype=np.int64)
        hands = []
        for side in [str(s) for s in _npz_get(data, "hand_sides")]:
            hand = HandTrack(side=cast(Any, side), valid=np.asarray(_npz_get(data, f"{side}_valid")))
            kp = _npz_get(data, f"{side}_keypoints", required=False)
            hand.keypoints = None if kp is None else _as_float(kp)
            if f"{side}_mano_hand_pose" in data.files:
                hand.mano = ManoParams(
                    global_orient=_as_float(_npz_get(data, f"{side}_mano_global_orient")),
                    hand_pose=_as_float(_npz_get(data, f"{side}_mano_hand_pose")),
                    trans=_as_float(_npz_get(data, f"{side}_mano_trans")),
                    betas=_as_float(_npz_get(data, f"{side}_mano_betas")),
                    pose_format=cast(Any, str(_npz_get(data, f"{side}_mano_pose_format"))),
                    flat_hand_mean=bool(_npz_get(data, f"{side}_mano_flat_hand_mean")),
                )
            hands.append(hand)
        wfc = _npz_get(data, "world_from_camera", required=False)
        up = _npz_get(data, "up", required=False)
        meta_raw = _npz_get(data, "meta_json", required=False)
        seq = Sequence(
            name=str(_npz_get(data, "name")),
            fps=float(_npz_get(data, "fps")),
            frame_start=int(_npz_get(data, "frame_start", required=False) or 0),
            object=obj,
            object_pose=_as_float(_npz_get(data, "object_pose")),
            hands=hands,
            world_from_source=None if wfc is None else _as_float(wfc),
            up=None if up is None else _as_float(up),
            meta={} if meta_raw is None else json.loads(str(meta_raw)),
        )
    return seq.validate(max_frames=max_frames)


def _opt_float(x: Any) -> float | None:
    return None if x is None else float(x)


# ---------------------------------------------------------------------- JSON


def sequence_to_json_dict(seq: Sequence) -> dict[str, Any]:
    """The native JSON form (mesh inline), suitable for ``POST /v1/jobs``."""
    obj = seq.object
    obj_d: dict[str, Any] = {"name": obj.name, "mass_kg": obj.mass_kg}
    if obj.friction is not None:
        obj_d["friction"] = obj.friction
    if obj.primitive is not None:
        assert obj.size is not None
        obj_d["primitive"] = {"kind": obj.primitive, "size": obj.size.tolist()}
    else:
        assert obj.mesh_vertices is not None and obj.mesh_faces is not None
        obj_d["mesh"] = {"vertices": obj.mesh_vertices.tolist(), "faces": obj.mesh_faces.tolist()}
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
        "format_version": FORMAT_VERSION,
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
    return out


def sequence_from_json_dict(
    doc: Any, base_dir: Path | None = None, max_frames: int | None = None
) -> Sequence:
    """Parse the native JSON form and validate. ``base_dir`` resolves ``object.mesh_file``."""
    problems: list[FieldProblem] = []

    def need(d: Any, key: str, path: str) -> Any:
        if not isinstance(d, dict) or key not in d:
            problems.append(FieldProblem(path, "is required"))
            return None
        return d[key]

    def arr(value: Any, path: str, dtype: Any = np.float64) -> Any:
        if value is None:
            return None
        try:
            return np.asarray(value, dtype=dtype)
        except (ValueError, TypeError, OverflowError):
            problems.append(FieldProblem(path, "must be a (nested) list of numbers of a regular shape"))
            return None

    def num(value: Any, path: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            if value is not None:
                problems.append(FieldProblem(path, f"must be a number, got {type(value).__name__}"))
            return float("nan")
        return float(value)

    if not isinstance(doc, dict):
        raise SequenceValidationError.single("body", "must be a JSON object")
    if doc.get("format", FORMAT_NAME) != FORMAT_NAME:
        raise SequenceValidationError.single("format", f"expected {FORMAT_NAME!r}")
    if doc.get("format_version", FORMAT_VERSION) != FORMAT_VERSION:
        raise SequenceValidationError.single("format_version", f"this build reads version {FORMAT_VERSION}")

    od = need(doc, "object", "object") or {}
    obj = ObjectSpec(
        name=str(od.get("name", "object")) if isinstance(od, dict) else "object",
        mass_kg=num(need(od, "mass_kg", "object.mass_kg"), "object.mass_kg"),
        friction=None if not isinstance(od, dict) or od.get("friction") is None
        else num(od["friction"], "object.friction"),
    )
    if isinstance(od, dict):
        if "primitive" in od:
            prim = od["primitive"]
            kind = prim.get("kind") if isinstance(prim, dict) else None
            if kind not in PRIMITIVE_SIZE_LEN:
                problems.append(FieldProblem("object.primitive.kind", f"must be one of {sorted(PRIMITIVE_SIZE_LEN)}"))
            else:
                obj.primitive = kind
                obj.size = arr(prim.get("size"), "object.primitive.size")
                if prim.get("size") is None:
                    problems.append(FieldProblem("object.primitive.size", "is required"))
        if "mesh" in od:
            mesh = od["mesh"] if isinstance(od["mesh"], dict) else {}
            obj.mesh_vertices = arr(need(mesh, "vertices", "object.mesh.vertices"), "object.mesh.vertices")
            obj.mesh_faces = arr(need(mesh, "faces", "object.mesh.faces"), "object.mesh.faces", np.int64)
        if "mesh_file" in od:
            mesh_path = Path(str(od["mesh_file"]))
            if not mesh_path.is_absolute() and base_dir is not None:
                mesh_path = base_dir / mesh_path
            obj.mesh_vertices, obj.mesh_faces = load_mesh_file(mesh_path)

    hands = []
    hand_docs = need(doc, "hands", "hands")
    if hand_docs is not None and not isinstance(hand_docs, list):
        problems.append(FieldProblem("hands", "must be a list"))
        hand_docs = []
    for i, hd in enumerate(hand_docs or []):
        p = f"hands[{i}]"
        if not isinstance(hd, dict):
            problems.append(FieldProblem(p, "must be an object"))
            continue
        valid = arr(need(hd, "valid", f"{p}.valid"), f"{p}.valid", None)
        if valid is not None and valid.dtype != np.bool_:
            problems.append(FieldProblem(f"{p}.valid", "must be a list of booleans"))
        hand = HandTrack(
            side=cast(Any, hd.get("side")),  # validated in Sequence.validate
            valid=valid if valid is not None else np.zeros(0, dtype=bool),
            keypoints=arr(hd.get("keypoints"), f"{p}.keypoints"),
        )
        md = hd.get("mano")
        if isinstance(md, dict):
            hand.mano = ManoParams(
                global_orient=arr(need(md, "global_orient", f"{p}.mano.global_orient"), f"{p}.mano.global_orient"),
                hand_pose=arr(need(md, "hand_pose", f"{p}.mano.hand_pose"), f"{p}.mano.hand_pose"),
                trans=arr(need(md, "trans", f"{p}.mano.trans"), f"{p}.mano.trans"),
                betas=arr(md.get("betas", [0.0] * 10), f"{p}.mano.betas"),
                pose_format=md.get("pose_format", "axis_angle"),
                flat_hand_mean=bool(md.get("flat_hand_mean", False)),
            )
        hands.append(hand)

    fps = num(need(doc, "fps", "fps"), "fps")
    pose = arr(need(doc, "object_pose", "object_pose"), "object_pose")
    frame_start = doc.get("frame_start", 0)
    if not isinstance(frame_start, int) or isinstance(frame_start, bool):
        problems.append(FieldProblem("frame_start", "must be an integer"))
        frame_start = 0
    if problems:
        raise SequenceValidationError(problems)
    seq = Sequence(
        name=str(doc.get("name", "sequence")),
        fps=fps,
        frame_start=frame_start,
        object=obj,
        object_pose=pose,
        hands=hands,
        world_from_source=arr(doc.get("world_from_camera"), "world_from_camera"),
        up=arr(doc.get("up"), "up"),
        meta={str(k): str(v) for k, v in (doc.get("meta") or {}).items()},
    )
    return seq.validate(max_frames=max_frames)


# ---------------------------------------------------------------------- files


def load_sequence(path: Path | str, max_frames: int | None = None) -> Sequence:
    """Read a sequence file, choosing the format by suffix (``.npz`` or ``.json``), or a DexYCB sequence folder."""
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
        try:
            doc = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise UnsupportedFormatError(f"{path.name} is not valid JSON: {exc}") from exc
        return sequence_from_json_dict(doc, base_dir=path.parent, max_frames=max_frames)
    raise UnsupportedFormatError(f"{path.name}: unknown sequence format {suffix!r} (expected .npz or .json)")


def save_sequence(seq: Sequence, path: Path | str) -> None:
    path = Path(path)
    if path.suffix.lower() == ".json":
        path.write_text(json.dumps(sequence_to_json_dict(seq)))
    else:
        path.write_bytes(sequence_to_npz_bytes(seq))
