"""Write the bad-input corpus: ``tests/corpus/bad_inputs/*`` and ``manifest.json`` (issue #16).

Each case is one submission that must be refused with its status and a problem naming its field:
``kind`` "npz" (multipart ``sequence`` part, with ``options`` when given), "json" (an application/json
body: the native JSON sequence plus options). Cases start from a valid 5-frame sequence and break one
thing: types, dtypes, shapes, finiteness, sizes, strings (NUL, control, bidi), the zip container (lying
sizes, bomb-like declared shapes, pickles, foreign compression), options (Infinity, NaN, unknown names).

The files are committed; ``tests/integration/test_bad_input_corpus.py`` checks that this script still
writes exactly them, then sends each through the API on SQLite and PostgreSQL. Regenerate with
``python -m tests.corpus.make_bad_inputs``.
"""

from __future__ import annotations

import io
import json
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from common.npz_writer import FIXED_DATE_TIME, deterministic_npz_bytes, npy_bytes
from common.sequence_io import sequence_to_json_dict, sequence_to_npz_bytes
from tests.support.articulated import tiny_articulated_sequence
from tests.support.queue_fixtures import tiny_sequence

OUT = Path(__file__).resolve().parent / "bad_inputs"
Arrays = dict[str, Any]


def base_arrays() -> Arrays:
    with np.load(io.BytesIO(sequence_to_npz_bytes(tiny_sequence(0).validate()))) as data:
        return {k: data[k] for k in data.files}


def base_json(articulated: bool = False) -> dict[str, Any]:
    seq = tiny_articulated_sequence(0) if articulated else tiny_sequence(0)
    doc = sequence_to_json_dict(seq.validate())
    doc["options"] = {"seed": 0}
    return doc


def articulated_arrays() -> Arrays:
    with np.load(io.BytesIO(sequence_to_npz_bytes(tiny_articulated_sequence(0).validate()))) as data:
        return {k: data[k] for k in data.files}


def articulated_npz_with(change: Callable[[Arrays], None]) -> bytes:
    arrays = articulated_arrays()
    change(arrays)
    return deterministic_npz_bytes(arrays)


def raw_zip(members: dict[str, bytes], compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression) as zf:
        for name, data in members.items():
            zf.writestr(zipfile.ZipInfo(name, FIXED_DATE_TIME), data, compress_type=compression)
    return buf.getvalue()


def npz_with(change: Callable[[Arrays], None]) -> bytes:
    arrays = base_arrays()
    change(arrays)
    return deterministic_npz_bytes(arrays)


def members_of(arrays: Arrays) -> dict[str, bytes]:
    return {f"{k}.npy": npy_bytes(v) for k, v in arrays.items()}


def _set(**values: Any) -> Callable[[Arrays], None]:
    def change(arrays: Arrays) -> None:
        for key, value in values.items():
            if value is None:
                arrays.pop(key, None)
            else:
                arrays[key] = value

    return change


def _pose(edit: Callable[[np.ndarray], np.ndarray]) -> Callable[[Arrays], None]:
    return lambda a: a.__setitem__("object_pose", edit(a["object_pose"].copy()))


def _bigger_than_declared() -> bytes:
    """object_pose whose .npy header says (5, 7) but whose entry holds 1000 rows: the sizes disagree."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (5, 7)})
    members = members_of(base_arrays())
    members["object_pose.npy"] = header.getvalue() + np.zeros((1000, 7)).tobytes()
    return raw_zip(members)


def _declares_huge_shape() -> bytes:
    """A bomb: 100000 frames of zeros (5.6 MB inflated, a few KB deflated); refused from the header."""
    return npz_with(_set(object_pose=np.zeros((100_000, 7))))


def _pickled_member() -> bytes:
    members = members_of(base_arrays())
    out = io.BytesIO()
    np.lib.format.write_array(out, np.array([{"a": 1}, None], dtype=object), allow_pickle=True)
    members["object_pose.npy"] = out.getvalue()
    return raw_zip(members)


def _bz2_member() -> bytes:
    return raw_zip(members_of(base_arrays()), zipfile.ZIP_BZIP2)


def _duplicate_member() -> bytes:
    buf = io.BytesIO(raw_zip(members_of(base_arrays())))
    with zipfile.ZipFile(buf, "a") as zf, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zipfile warns about the duplicate name: that is the point
        zf.writestr(zipfile.ZipInfo("name.npy", FIXED_DATE_TIME), npy_bytes(np.array("again")))
    return buf.getvalue()


def _many_members() -> bytes:
    members = members_of(base_arrays())
    members.update({f"extra{i}.npy": npy_bytes(np.zeros(1)) for i in range(140)})
    return raw_zip(members)


def _odd_member_name() -> bytes:
    members = members_of(base_arrays())
    members["\u202eevil.npy"] = npy_bytes(np.zeros(1))
    return raw_zip(members)


def _not_npy_member() -> bytes:
    members = members_of(base_arrays())
    members["readme.txt"] = b"hello"
    return raw_zip(members)


def _truncated() -> bytes:
    blob = sequence_to_npz_bytes(tiny_sequence(0).validate())
    return blob[: len(blob) // 2]


def _dexycb(change: Callable[[Arrays], None] | None = None) -> bytes:
    arrays: Arrays = {
        "fps": np.array(30.0), "side": np.array("right"), "object_name": np.array("011_banana"),
        "hand_joints": np.full((5, 21, 3), 0.05, np.float32), "hand_valid": np.ones(5, bool),
        "object_pose": np.tile(np.array([0, 0, 0.5, 1, 0, 0, 0], np.float32), (5, 1)),
        "world_from_camera": np.eye(4),
    }  # fmt: skip
    if change is not None:
        change(arrays)
    return deterministic_npz_bytes(arrays)


def _mano(hand_pose_cols: int, pose_format: str) -> Callable[[Arrays], None]:
    def change(a: Arrays) -> None:
        a["right_mano_global_orient"] = np.zeros((5, 3))
        a["right_mano_hand_pose"] = np.zeros((5, hand_pose_cols))
        a["right_mano_trans"] = np.zeros((5, 3))
        a["right_mano_betas"] = np.zeros(10)
        a["right_mano_pose_format"] = np.array(pose_format)
        a["right_mano_flat_hand_mean"] = np.array(False)

    return change


def _nested(depth: int) -> str:
    return "[" * depth + "]" * depth


# (file stem, bytes or JSON document, expected field, note[, options JSON for multipart])
NPZ_CASES: list[tuple[str, Callable[[], bytes], str, str]] = [
    ("not_a_zip", lambda: b"this is not a zip file at all", "sequence", "random bytes"),
    ("empty_file", lambda: b"", "sequence", "zero bytes"),
    ("truncated_zip", _truncated, "sequence", "half of a valid file"),
    ("member_not_npy", _not_npy_member, "sequence", "a readme.txt member"),
    ("member_name_bidi", _odd_member_name, "sequence", "a member named with U+202E"),
    ("too_many_members", _many_members, "sequence", "140 extra members"),
    ("duplicate_member", _duplicate_member, "sequence", "name.npy twice"),
    ("bzip2_member", _bz2_member, "format", "members compressed with bzip2"),
    ("pickled_object_pose", _pickled_member, "object_pose", "an object (pickle) array"),
    ("lying_member_size", _bigger_than_declared, "object_pose", "header says 5 frames, entry holds 1000"),
    ("bomb_100k_frames", _declares_huge_shape, "object_pose", "100000 frames declared, over the limit"),
    ("pose_structured_dtype", lambda: npz_with(_set(object_pose=np.zeros(5, dtype=[("x", "<f8"), ("y", "<f8")]))),
     "object_pose", "structured dtype"),
    ("pose_string", lambda: npz_with(_set(object_pose=np.array("0 0 0 1 0 0 0"))), "object_pose", "a string"),
    ("pose_1d", lambda: npz_with(_set(object_pose=np.zeros(35))), "object_pose", "1-D instead of (T, 7)"),
    ("pose_6_columns", lambda: npz_with(_set(object_pose=np.zeros((5, 6)))), "object_pose", "(T, 6)"),
    ("pose_nan", lambda: npz_with(_pose(lambda p: np.where(np.arange(7) == 0, np.nan, p))), "object_pose", "NaN"),
    ("pose_inf", lambda: npz_with(_pose(lambda p: np.where(np.arange(7) == 1, np.inf, p))), "object_pose", "Inf"),
    ("pose_one_frame", lambda: npz_with(_set(object_pose=np.array([[0, 0, 0.02, 1, 0, 0, 0.0]]),
                                             right_valid=np.ones(1, bool), right_keypoints=np.zeros((1, 21, 3)))),
     "object_pose", "1 frame: below the 2-frame minimum"),
    ("pose_zero_frames", lambda: npz_with(_set(object_pose=np.zeros((0, 7)))), "object_pose", "no frames"),
    ("pose_not_unit", lambda: npz_with(_pose(lambda p: p * 2)), "object_pose", "quaternion of norm 2"),
    ("pose_huge", lambda: npz_with(_pose(lambda p: p + np.array([1e300, 0, 0, 0, 0, 0, 0]))), "object_pose",
     "1e300 m"),
    ("fps_string", lambda: npz_with(_set(fps=np.array("thirty"))), "fps", "a string"),
    ("fps_array", lambda: npz_with(_set(fps=np.array([30.0, 30.0]))), "fps", "an array"),
    ("fps_negative", lambda: npz_with(_set(fps=np.array(-30.0))), "fps", "negative"),
    ("fps_nan", lambda: npz_with(_set(fps=np.array(np.nan))), "fps", "NaN"),
    ("fps_huge", lambda: npz_with(_set(fps=np.array(1e9))), "fps", "1e9 frames per second"),
    ("format_wrong", lambda: npz_with(_set(format=np.array("something-else"))), "format", "another format"),
    ("format_version_3", lambda: npz_with(_set(format_version=np.array(3))), "format_version", "version 3"),
    ("format_version_2_rigid", lambda: npz_with(_set(format_version=np.array(2))), "object_base_part",
     "version 2 (articulated) without its members"),
    ("format_version_float", lambda: npz_with(_set(format_version=np.array(1.0))), "format_version", "a float"),
    ("name_nul", lambda: npz_with(_set(name=np.array("seq\x00name"))), "name", "NUL in the name"),
    ("name_bidi", lambda: npz_with(_set(name=np.array("abc\u202etxt.exe"))), "name", "U+202E in the name"),
    ("name_newline", lambda: npz_with(_set(name=np.array("two\nlines"))), "name", "a newline in the name"),
    ("name_number", lambda: npz_with(_set(name=np.array([1.0, 2.0]))), "name", "numbers"),
    ("name_too_long", lambda: npz_with(_set(name=np.array("x" * 300))), "name", "300 characters"),
    ("object_name_control", lambda: npz_with(_set(object_name=np.array("box\x1b[31m"))), "object.name",
     "an ANSI escape"),
    ("mass_missing", lambda: npz_with(_set(object_mass_kg=None)), "object_mass_kg", "no mass"),
    ("mass_zero", lambda: npz_with(_set(object_mass_kg=np.array(0.0))), "object.mass_kg", "0 kg"),
    ("mass_string", lambda: npz_with(_set(object_mass_kg=np.array("heavy"))), "object_mass_kg", "a string"),
    ("primitive_unknown", lambda: npz_with(_set(object_primitive=np.array("torus"))), "object.primitive", "torus"),
    ("size_wrong_length", lambda: npz_with(_set(object_size=np.array([0.02, 0.02]))), "object.size", "2 for a box"),
    ("size_negative", lambda: npz_with(_set(object_size=np.array([0.02, -0.02, 0.02]))), "object.size", "negative"),
    ("mesh_faces_out_of_range", lambda: npz_with(_set(
        object_primitive=None, object_size=None, object_mesh_vertices=np.eye(4)[:, :3] * 0.05,
        object_mesh_faces=np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 9]]))), "object.mesh.faces",
     "index 9 of 4 vertices"),
    ("mesh_vertices_2d", lambda: npz_with(_set(
        object_primitive=None, object_size=None, object_mesh_vertices=np.zeros((4, 2)),
        object_mesh_faces=np.zeros((4, 3), int))), "object_mesh_vertices", "(V, 2)"),
    ("mesh_faces_float", lambda: npz_with(_set(
        object_primitive=None, object_size=None, object_mesh_vertices=np.eye(4)[:, :3] * 0.05,
        object_mesh_faces=np.zeros((4, 3)))), "object_mesh_faces", "float faces"),
    ("sides_invalid", lambda: npz_with(_set(hand_sides=np.array(["middle"]))), "hand_sides", "'middle'"),
    ("sides_duplicate", lambda: npz_with(_set(hand_sides=np.array(["right", "right"]))), "hand_sides", "twice"),
    ("sides_2d", lambda: npz_with(_set(hand_sides=np.array([["right"]]))), "hand_sides", "2-D"),
    ("valid_missing", lambda: npz_with(_set(right_valid=None)), "right_valid", "no validity mask"),
    ("valid_int", lambda: npz_with(_set(right_valid=np.ones(5, int))), "right_valid", "integers"),
    ("valid_all_false", lambda: npz_with(_set(right_valid=np.zeros(5, bool))), "hands[0].valid", "no valid frame"),
    ("valid_length", lambda: npz_with(_set(right_valid=np.ones(4, bool))), "hands[0].valid", "4 of 5 frames"),
    ("keypoints_20_joints", lambda: npz_with(_set(right_keypoints=np.zeros((5, 20, 3)))), "right_keypoints",
     "20 joints"),
    ("keypoints_nan", lambda: npz_with(_set(right_keypoints=np.full((5, 21, 3), np.nan))), "right_keypoints", "NaN"),
    ("hand_without_data", lambda: npz_with(_set(right_keypoints=None)), "hands[0]", "no keypoints, no MANO"),
    ("mano_hand_pose_44", lambda: npz_with(_mano(44, "axis_angle")), "hands[0].mano.hand_pose", "44 of 45"),
    ("mano_pose_format", lambda: npz_with(_mano(45, "euler")), "hands[0].mano.pose_format", "euler"),
    ("meta_list", lambda: npz_with(_set(meta_json=np.array("[1, 2, 3]"))), "meta_json", "a JSON list"),
    ("meta_invalid_json", lambda: npz_with(_set(meta_json=np.array("{not json"))), "meta_json", "broken JSON"),
    ("meta_deep", lambda: npz_with(_set(meta_json=np.array(_nested(50_000)))), "meta_json", "50000 levels"),
    ("meta_numbers", lambda: npz_with(_set(meta_json=np.array('{"a": 1}'))), "meta_json", "a number value"),
    ("meta_value_nul", lambda: npz_with(_set(meta_json=np.array('{"source": "a\\u0000b"}'))), "meta.source",
     "NUL in a meta value"),
    ("world_not_rigid", lambda: npz_with(_set(up=None, world_from_camera=np.eye(4) * 2)), "world_from_camera",
     "scaled"),
    ("world_3x4", lambda: npz_with(_set(up=None, world_from_camera=np.eye(4)[:3])), "world_from_camera", "(3, 4)"),
    ("up_zero", lambda: npz_with(_set(up=np.zeros(3))), "up", "zero vector"),
    ("frame_start_negative", lambda: npz_with(_set(frame_start=np.array(-1))), "frame_start", "-1"),
    ("dexycb_without_ycb_dir", _dexycb, "sequence", "a DexYCB file on a server without HOI_REFINE_YCB_DIR"),
    ("dexycb_joints_shape", lambda: _dexycb(_set(hand_joints=np.zeros((5, 3)))), "hand_joints", "(T, 3)"),
    # An articulated object (issue #52): the tiny hinged box with one thing broken.
    ("arti_axis_zero", lambda: articulated_npz_with(_set(object_joint_axes=np.zeros((1, 3)))),
     "object.parts[0].joint.axis", "a joint axis of zero length"),
    ("arti_value_outside_limits", lambda: articulated_npz_with(_set(
        object_articulation=np.array([[0.0], [0.1], [2.0], [0.3], [0.4]]))), "articulation", "2 rad, limits [0, 1.5]"),
    ("arti_part_without_mesh", lambda: articulated_npz_with(_set(object_part0_primitive=None, object_part0_size=None)),
     "object_part0_mesh_vertices", "a part with neither a primitive nor a mesh"),
    ("arti_unknown_parent", lambda: articulated_npz_with(_set(object_joint_parents=np.array(["nowhere"]))),
     "object.parts[0].joint.parent", "a parent no part is called"),
    ("arti_articulation_shape", lambda: articulated_npz_with(_set(object_articulation=np.zeros((5, 2)))),
     "object_articulation", "(T, 2) for one joint"),
    ("arti_articulation_missing", lambda: articulated_npz_with(_set(object_articulation=None)), "object_articulation",
     "no joint values"),
    ("arti_joint_type", lambda: articulated_npz_with(_set(object_joint_types=np.array(["ball"]))),
     "object.parts[0].joint.type", "a ball joint"),
    ("arti_limits_reversed", lambda: articulated_npz_with(_set(object_joint_limits=np.array([[1.0, 0.0]]))),
     "object.parts[0].joint.limits", "lower above upper"),
    ("arti_joint_axes_rows", lambda: articulated_npz_with(_set(object_joint_axes=np.zeros((2, 3)))),
     "object_joint_axes", "two axes for one joint"),
    ("arti_part_name_nul", lambda: articulated_npz_with(_set(object_part_names=np.array(["li\x00d"]))),
     "object.parts[0].name", "NUL in a part name"),
]

OPTION_CASES: list[tuple[str, str, str, str]] = [
    ("options_weight_infinity", '{"loss_weights": {"object_pose": Infinity}}', "options.loss_weights.object_pose",
     "Infinity"),
    ("options_weight_nan", '{"loss_weights": {"object_pose": NaN}}', "options.loss_weights.object_pose", "NaN"),
    ("options_weight_negative", '{"loss_weights": {"hand_joints": -1}}', "options.loss_weights.hand_joints", "-1"),
    ("options_unknown", '{"turbo": true}', "options.turbo", "no such option"),
    ("options_not_json", "{seed: 1", "options", "broken JSON"),
    ("options_seed_huge", '{"seed": 99999999999999999999}', "options.seed", "beyond 2**31-1"),
]


def _json_case(change: Callable[[dict[str, Any]], Any]) -> Callable[[], bytes]:
    def make() -> bytes:
        doc = base_json()
        out = change(doc)
        return out if isinstance(out, bytes) else json.dumps(doc if out is None else out).encode()

    return make


def _arti_json(change: Callable[[dict[str, Any]], Any]) -> Callable[[], bytes]:
    def make() -> bytes:
        doc = base_json(articulated=True)
        change(doc)
        return json.dumps(doc).encode()

    return make


def _joint(doc: dict[str, Any]) -> dict[str, Any]:
    joint: dict[str, Any] = doc["object"]["parts"][0]["joint"]
    return joint


def _replace_number(doc: dict[str, Any], key: str, literal: str) -> bytes:
    doc[key] = 12345.5
    return json.dumps(doc).encode().replace(b"12345.5", literal.encode())


def _one_frame(doc: dict[str, Any]) -> None:
    doc["object_pose"] = doc["object_pose"][:1]
    doc["hands"][0]["valid"] = [True]
    doc["hands"][0]["keypoints"] = doc["hands"][0]["keypoints"][:1]


JSON_CASES: list[tuple[str, Callable[[], bytes], str, str]] = [
    ("json_not_json", lambda: b"{not json", "body", "broken JSON"),
    ("json_deep", lambda: _nested(5_000).encode(), "body", "5000 levels of lists"),
    ("json_top_list", _json_case(lambda d: [d]), "body", "a list, not an object"),
    ("json_fps_nan", _json_case(lambda d: _replace_number(d, "fps", "NaN")), "fps", "NaN literal"),
    ("json_fps_infinity", _json_case(lambda d: _replace_number(d, "fps", "Infinity")), "fps", "Infinity literal"),
    ("json_meta_list", _json_case(lambda d: d.__setitem__("meta", ["a"])), "meta", "meta as a list"),
    ("json_name_nul", _json_case(lambda d: d.__setitem__("name", "a\x00b")), "name", "NUL"),
    ("json_name_bidi", _json_case(lambda d: d.__setitem__("name", "\u2066hidden\u2069")), "name", "U+2066"),
    ("json_hands_object", _json_case(lambda d: d.__setitem__("hands", {"side": "right"})), "hands", "not a list"),
    ("json_one_frame", _json_case(_one_frame), "object_pose", "1 frame"),
    ("json_pose_string", _json_case(lambda d: d.__setitem__("object_pose", "0 0 0 1 0 0 0")), "object_pose",
     "a string"),
    ("json_frame_start_huge", _json_case(lambda d: d.__setitem__("frame_start", 10**20)), "frame_start", "1e20"),
    ("json_unknown_field_bidi", _json_case(lambda d: d.__setitem__("\u202eevil", 1)), "'\\u202eevil'",
     "an unknown member whose name is escaped when echoed"),
    ("json_weight_infinity", _json_case(
        lambda d: json.dumps({**d, "options": {"loss_weights": {"hand_joints": 7.5}}}).encode().replace(
            b"7.5", b"Infinity")), "options.loss_weights.hand_joints", "Infinity loss weight"),
    ("json_mass_huge", _json_case(lambda d: d["object"].__setitem__("mass_kg", 1e308)), "object.mass_kg", "1e308 kg"),
    ("json_arti_axis_zero", _arti_json(lambda d: _joint(d).__setitem__("axis", [0.0, 0.0, 0.0])),
     "object.parts[0].joint.axis", "a joint axis of zero length"),
    ("json_arti_value_outside_limits", _arti_json(lambda d: d["articulation"][2].__setitem__(0, -1.0)), "articulation",
     "-1 rad, limits [0, 1.5]"),
    ("json_arti_part_without_mesh", _arti_json(lambda d: d["object"]["parts"][0].pop("primitive")), "object.parts[0]",
     "a part with neither a primitive nor a mesh"),
    ("json_arti_unknown_parent", _arti_json(lambda d: _joint(d).__setitem__("parent", "nowhere")),
     "object.parts[0].joint.parent", "a parent no part is called"),
    ("json_arti_articulation_shape", _arti_json(lambda d: d.__setitem__("articulation", [[0.0, 0.0]] * 5)),
     "articulation", "(T, 2) for one joint"),
    ("json_arti_articulation_ragged", _arti_json(lambda d: d["articulation"].__setitem__(1, [0.1, 0.2])),
     "articulation", "rows of different lengths"),
    ("json_arti_articulation_missing", _arti_json(lambda d: d.pop("articulation")), "articulation", "no joint values"),
    ("json_arti_joint_type", _arti_json(lambda d: _joint(d).__setitem__("type", "ball")), "object.parts[0].joint.type",
     "a ball joint"),
    ("json_arti_axis_length", _arti_json(lambda d: _joint(d).__setitem__("axis", [1.0, 0.0])),
     "object.parts[0].joint.axis", "two numbers"),
    ("json_arti_rigid_with_articulation", _json_case(lambda d: d.__setitem__("articulation", [[0.0]] * 5)),
     "articulation", "joint values for a rigid object"),
]


def cases() -> tuple[dict[str, bytes], list[dict[str, Any]]]:
    files: dict[str, bytes] = {}
    manifest: list[dict[str, Any]] = []
    for stem, make, field, note in NPZ_CASES:
        files[f"{stem}.npz"] = make()
        manifest.append({"file": f"{stem}.npz", "kind": "npz", "status": 422, "field": field, "note": note})
    valid = sequence_to_npz_bytes(tiny_sequence(0).validate())
    for stem, options, field, note in OPTION_CASES:
        files[f"{stem}.npz"] = valid
        manifest.append({"file": f"{stem}.npz", "kind": "npz", "options": options, "status": 422, "field": field,
                         "note": note})  # fmt: skip
    for stem, make, field, note in JSON_CASES:
        files[f"{stem}.json"] = make()
        manifest.append({"file": f"{stem}.json", "kind": "json", "status": 422, "field": field, "note": note})
    return files, manifest


def main() -> None:
    files, manifest = cases()
    OUT.mkdir(parents=True, exist_ok=True)
    for old in OUT.iterdir():
        old.unlink()
    for name, data in files.items():
        (OUT / name).write_bytes(data)
    (OUT / "manifest.json").write_text(json.dumps(manifest, indent=1, ensure_ascii=True) + "\n")
    print(f"wrote {len(manifest)} cases to {OUT}")


if __name__ == "__main__":
    main()
