"""The articulated sequence format (issue #52 item 1, "must show"): NPZ and JSON round-trips (re-saving is
bit-identical), every joint field kept, rigid files still version 1; bad articulated inputs named by field, every
problem at once."""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from common.articulation import MAX_PARTS
from common.errors import SequenceValidationError
from common.npz_writer import deterministic_npz_bytes
from common.sequence import Sequence
from common.sequence_io import (
    sequence_from_json_bytes,
    sequence_from_json_dict,
    sequence_from_npz_bytes,
    sequence_to_json_dict,
    sequence_to_npz_bytes,
)
from tests.support.articulated import drawer_cabinet_sequence, tiny_articulated_sequence


def _json_bytes(seq: Sequence) -> bytes:
    return json.dumps(sequence_to_json_dict(seq)).encode()


def _assert_same_object(a: Sequence, b: Sequence) -> None:
    assert a.object.part_names == b.object.part_names and a.object.base_part == b.object.base_part
    for pa, pb in zip(a.object.part_shapes(), b.object.part_shapes(), strict=True):
        assert (pa.name, pa.mass_kg, pa.friction, pa.primitive) == (pb.name, pb.mass_kg, pb.friction, pb.primitive)
        for key in ("size", "mesh_vertices", "mesh_faces"):
            va, vb = getattr(pa, key), getattr(pb, key)
            assert (va is None) == (vb is None) and (va is None or np.array_equal(va, vb))
    for ja, jb in zip(a.object.joints, b.object.joints, strict=True):
        assert (ja.name, ja.kind, ja.parent, ja.damping, ja.friction) == (jb.name, jb.kind, jb.parent, jb.damping,
                                                                          jb.friction)  # fmt: skip
        for key in ("axis", "origin_pos", "origin_quat", "limits"):
            np.testing.assert_array_equal(getattr(ja, key), getattr(jb, key))
    np.testing.assert_array_equal(a.articulation, b.articulation)
    np.testing.assert_array_equal(a.object_pose, b.object_pose)


@pytest.mark.parametrize("make", [lambda: tiny_articulated_sequence().validate(),
                                  lambda: drawer_cabinet_sequence(mano=True).validate()], ids=["hinged", "cabinet"])
def test_articulated_sequences_round_trip_bit_identically(make: Callable[[], Sequence]) -> None:
    seq = make()
    npz = sequence_to_npz_bytes(seq)
    with np.load(io.BytesIO(npz)) as data:
        assert int(data["format_version"]) == 2
    from_npz = sequence_from_npz_bytes(npz)
    _assert_same_object(seq, from_npz)
    assert sequence_to_npz_bytes(from_npz) == npz  # re-saving is bit-identical
    text = _json_bytes(seq)
    assert json.loads(text)["format_version"] == 2
    from_json = sequence_from_json_bytes(text)
    _assert_same_object(seq, from_json)
    assert _json_bytes(from_json) == text
    # Across the formats: NPZ -> JSON -> NPZ and JSON -> NPZ -> JSON keep every bit.
    assert sequence_to_npz_bytes(sequence_from_json_bytes(_json_bytes(from_npz))) == npz
    assert _json_bytes(sequence_from_npz_bytes(sequence_to_npz_bytes(from_json))) == text
    # Forward kinematics of the loaded copies agree exactly.
    for other in (from_npz, from_json):
        np.testing.assert_array_equal(other.object.part_poses(other.object_pose, other.articulation),
                                      seq.object.part_poses(seq.object_pose, seq.articulation))  # fmt: skip


def test_joint_fields_survive_and_axes_are_normalised_once() -> None:
    seq = drawer_cabinet_sequence().validate()
    slide = seq.object.joints[1]
    np.testing.assert_allclose(slide.axis, [0.0, -0.6, 0.8])
    assert slide.kind == "prismatic" and slide.damping == 0.5 and slide.friction == 0.02
    assert seq.object.parts[1].shape.friction == 0.7 and seq.object.joints[2].parent == "drawer"
    again = sequence_from_npz_bytes(sequence_to_npz_bytes(seq))
    assert again.object.joints[1].axis.tobytes() == slide.axis.tobytes()
    assert again.object.parts[1].shape.friction == 0.7
    # The prismatic drawer moves along its axis in the cabinet's frame: 0.2 m at the last frame.
    poses = again.object.part_poses(again.object_pose, again.articulation)
    np.testing.assert_allclose(poses[-1, 2, :3] - poses[0, 2, :3], 0.2 * np.array([0.0, -0.6, 0.8]), atol=1e-12)


def test_the_largest_articulated_object_with_two_mano_hands_fits_one_npz() -> None:
    seq = drawer_cabinet_sequence(parts=MAX_PARTS, mano=True).validate()
    npz = sequence_to_npz_bytes(seq)
    assert len(np.load(io.BytesIO(npz)).files) > 64
    assert sequence_to_npz_bytes(sequence_from_npz_bytes(npz)) == npz
    too_many = drawer_cabinet_sequence(parts=MAX_PARTS + 1)
    with pytest.raises(SequenceValidationError) as err:
        too_many.validate()
    assert [p.field for p in err.value.problems] == ["object.parts"]


def test_a_rigid_sequence_is_still_version_1() -> None:
    from tests.support.queue_fixtures import tiny_sequence

    seq = tiny_sequence().validate()
    npz = sequence_to_npz_bytes(seq)
    with np.load(io.BytesIO(npz)) as data:
        assert int(data["format_version"]) == 1 and "object_articulation" not in data.files
    assert sequence_to_json_dict(seq)["format_version"] == 1 and "articulation" not in sequence_to_json_dict(seq)
    assert sequence_from_npz_bytes(npz).articulation is None


# ---------------------------------------------------------------------------------------------- bad inputs
# Each case breaks one thing of the tiny hinged box in the JSON form and in the NPZ form, and names the field the
# answer must carry (the NPZ form names its member where its reader finds the problem before validation).
JsonEdit = Callable[[dict[str, Any]], None]
NpzEdit = Callable[[dict[str, Any]], None]


def _json_joint(key: str, value: Any) -> JsonEdit:
    return lambda d: d["object"]["parts"][0]["joint"].__setitem__(key, value)


def _drop_mesh_json(d: dict[str, Any]) -> None:
    d["object"]["parts"][0].pop("primitive")


def _drop_mesh_npz(a: dict[str, Any]) -> None:
    a.pop("object_part0_primitive")
    a.pop("object_part0_size")


def _set(key: str, value: Any) -> NpzEdit:
    return lambda a: a.__setitem__(key, value)


BAD_CASES: list[tuple[str, JsonEdit, str, NpzEdit, str, str]] = [
    ("zero axis", _json_joint("axis", [0.0, 0.0, 0.0]), "object.parts[0].joint.axis",
     _set("object_joint_axes", np.zeros((1, 3))), "object.parts[0].joint.axis", "zero length"),
    ("value outside its limits", lambda d: d["articulation"][3].__setitem__(0, 2.0), "articulation",
     _set("object_articulation", np.array([[0.0], [0.1], [0.2], [2.0], [0.4]])), "articulation", "outside its limits"),
    ("part without a mesh", _drop_mesh_json, "object.parts[0]",
     _drop_mesh_npz, "object_part0_mesh_vertices", "mesh"),
    ("unknown parent", _json_joint("parent", "nowhere"), "object.parts[0].joint.parent",
     _set("object_joint_parents", np.array(["nowhere"])), "object.parts[0].joint.parent", "must name"),
    ("wrong articulation shape", lambda d: d.__setitem__("articulation", [[0.0, 0.0]] * 5), "articulation",
     _set("object_articulation", np.zeros((5, 2))), "object_articulation", "shape"),
    ("articulation missing", lambda d: d.pop("articulation"), "articulation",
     lambda a: a.pop("object_articulation"), "object_articulation", ""),
    ("lower limit above upper", _json_joint("limits", [1.0, 0.5]), "object.parts[0].joint.limits",
     _set("object_joint_limits", np.array([[1.0, 0.5]])), "object.parts[0].joint.limits", "lower"),
    ("unknown joint type", _json_joint("type", "ball"), "object.parts[0].joint.type",
     _set("object_joint_types", np.array(["ball"])), "object.parts[0].joint.type", "revolute"),
]


def _json_doc() -> dict[str, Any]:
    return sequence_to_json_dict(tiny_articulated_sequence().validate())


def _npz_arrays() -> dict[str, Any]:
    with np.load(io.BytesIO(sequence_to_npz_bytes(tiny_articulated_sequence().validate()))) as data:
        return {k: data[k] for k in data.files}


@pytest.mark.parametrize("case", BAD_CASES, ids=[c[0] for c in BAD_CASES])
def test_bad_articulated_inputs_name_their_field(case: tuple[str, JsonEdit, str, NpzEdit, str, str]) -> None:
    _, json_edit, json_field, npz_edit, npz_field, words = case
    doc = _json_doc()
    json_edit(doc)
    with pytest.raises(SequenceValidationError) as err:
        sequence_from_json_dict(doc)
    assert json_field in [p.field for p in err.value.problems], err.value
    assert words in str(err.value)
    arrays = _npz_arrays()
    npz_edit(arrays)
    with pytest.raises(SequenceValidationError) as err:
        sequence_from_npz_bytes(deterministic_npz_bytes(arrays))
    assert npz_field in [p.field for p in err.value.problems], err.value


def test_every_joint_problem_is_reported_at_once() -> None:
    """A bad axis on one joint no longer hides a value outside another joint's limits, nor its own."""
    seq = drawer_cabinet_sequence(parts=3)
    seq.object.joints[0].axis = np.zeros(3)
    seq.object.joints[2].parent = "nowhere"
    assert seq.articulation is not None
    seq.articulation = seq.articulation.copy()
    seq.articulation[2, 1] = 0.9  # the drawer beyond its 0.25 m
    seq.articulation[4, 0] = 2.5  # the door beyond its 1.8 rad, though its axis is bad too
    with pytest.raises(SequenceValidationError) as err:
        seq.validate()
    fields = [p.field for p in err.value.problems]
    assert "object.parts[0].joint.axis" in fields and "object.parts[2].joint.parent" in fields
    limits = [p.problem for p in err.value.problems if p.field == "articulation"]
    assert len(limits) == 2 and "'drawer_slide' (column 1) is 0.9 at frame 2" in limits[1]
    assert "'door_hinge' (column 0) is 2.5 at frame 4" in limits[0]
