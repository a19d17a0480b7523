"""Every bad input is rejected with its field named (``common.sequence`` validation and the file formats)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from common.errors import SequenceValidationError
from common.sequence import HandTrack, ObjectSpec, Sequence
from common.sequence_io import (
    sequence_from_json_dict,
    sequence_from_npz_bytes,
    sequence_to_json_dict,
    sequence_to_npz_bytes,
)

T = 6


def _good() -> Sequence:
    rng = np.random.default_rng(0)
    pose = np.tile([0.0, 0.0, 0.03, 1.0, 0.0, 0.0, 0.0], (T, 1))
    return Sequence(
        name="ok",
        fps=30.0,
        object=ObjectSpec(name="box", mass_kg=0.2, primitive="box", size=np.array([0.03, 0.03, 0.03])),
        object_pose=pose,
        hands=[HandTrack(side="right", valid=np.ones(T, dtype=bool), keypoints=rng.normal(size=(T, 21, 3)))],
        world_from_source=np.eye(4),
    )


def _mesh(seq: Sequence, vertices: np.ndarray, faces: np.ndarray) -> None:
    seq.object.primitive, seq.object.size = None, None
    seq.object.mesh_vertices, seq.object.mesh_faces = vertices, faces


def _tetra() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int64)
    return v, f


def _set(attr: str, value: object) -> Callable[[Sequence], None]:
    def apply(seq: Sequence) -> None:
        obj: object = seq
        *path, last = attr.split(".")
        for part in path:
            obj = obj.hands[0] if part == "hand" else getattr(obj, part)  # type: ignore[attr-defined]
        setattr(obj, last, value)

    return apply


def _nan_keypoints(seq: Sequence) -> None:
    assert seq.hands[0].keypoints is not None
    seq.hands[0].keypoints[2, 5, 1] = np.nan


def _inf_pose(seq: Sequence) -> None:
    seq.object_pose[1, 0] = np.inf


def _non_unit_quat(seq: Sequence) -> None:
    seq.object_pose[3, 3:] = [0.9, 0.1, 0.0, 0.0]


def _degenerate_mesh(seq: Sequence) -> None:
    v, f = _tetra()
    v[:, 2] = 0.0  # flat
    _mesh(seq, v, f)


def _empty_mesh(seq: Sequence) -> None:
    _mesh(seq, np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))


def _bad_face_index(seq: Sequence) -> None:
    v, f = _tetra()
    f[0, 0] = 9
    _mesh(seq, v, f)


CASES: list[tuple[str, Callable[[Sequence], None], str]] = [
    ("fps zero", _set("fps", 0.0), "fps"),
    ("fps negative", _set("fps", -30.0), "fps"),
    ("fps NaN", _set("fps", float("nan")), "fps"),
    ("mass zero", _set("object.mass_kg", 0.0), "object.mass_kg"),
    ("mass negative", _set("object.mass_kg", -1.0), "object.mass_kg"),
    ("pose wrong shape", _set("object_pose", np.zeros((T, 6))), "object_pose"),
    ("pose Inf", _inf_pose, "object_pose"),
    ("non-unit quaternion", _non_unit_quat, "object_pose"),
    ("keypoints wrong shape", _set("hand.keypoints", np.zeros((T, 20, 3))), "hands[0].keypoints"),
    ("keypoints NaN", _nan_keypoints, "hands[0].keypoints"),
    ("keypoints frame count", _set("hand.keypoints", np.zeros((T + 1, 21, 3))), "hands[0].keypoints"),
    ("valid frame count", _set("hand.valid", np.ones(T - 1, dtype=bool)), "hands[0].valid"),
    ("valid not boolean", _set("hand.valid", np.ones(T)), "hands[0].valid"),
    ("no valid frame", _set("hand.valid", np.zeros(T, dtype=bool)), "hands[0].valid"),
    ("bad side", _set("hand.side", "middle"), "hands[0].side"),
    ("box size count", _set("object.size", np.array([0.1, 0.1])), "object.size"),
    ("box size negative", _set("object.size", np.array([0.1, -0.1, 0.1])), "object.size"),
    ("empty mesh", _empty_mesh, "object.mesh"),
    ("degenerate mesh", _degenerate_mesh, "object.mesh"),
    ("face index out of range", _bad_face_index, "object.mesh.faces"),
    ("not a rigid transform", _set("world_from_source", np.diag([2.0, 1.0, 1.0, 1.0])), "world_from_camera"),
    ("no hands", _set("hands", []), "hands"),
    ("empty name", _set("name", ""), "name"),
]


def test_good_sequence_validates() -> None:
    assert _good().validate() is not None


@pytest.mark.parametrize(("label", "mutate", "field"), CASES, ids=[c[0] for c in CASES])
def test_bad_input_names_its_field(label: str, mutate: Callable[[Sequence], None], field: str) -> None:
    seq = _good()
    mutate(seq)
    with pytest.raises(SequenceValidationError) as info:
        seq.validate()
    fields = [p.field for p in info.value.problems]
    assert field in fields, f"{label}: expected {field!r} among {fields}"
    assert field in str(info.value)


def test_more_frames_than_the_limit() -> None:
    with pytest.raises(SequenceValidationError, match=r"object_pose.*limit of 5"):
        _good().validate(max_frames=5)


def test_every_problem_is_reported_at_once() -> None:
    seq = _good()
    seq.fps = 0.0
    seq.object.mass_kg = -1.0
    with pytest.raises(SequenceValidationError) as info:
        seq.validate()
    assert {"fps", "object.mass_kg"} <= {p.field for p in info.value.problems}


def test_file_formats_round_trip_and_reject_bad_input() -> None:
    seq = _good().validate()
    back = sequence_from_npz_bytes(sequence_to_npz_bytes(seq))
    np.testing.assert_allclose(back.object_pose, seq.object_pose)
    d = sequence_to_json_dict(seq)
    np.testing.assert_allclose(
        np.asarray(sequence_from_json_dict(d).hands[0].keypoints), np.asarray(seq.hands[0].keypoints)
    )
    d["fps"] = -1
    with pytest.raises(SequenceValidationError, match="fps"):
        sequence_from_json_dict(d)


def test_normalising_quaternions_is_idempotent_so_a_saved_sequence_loads_bit_identical() -> None:
    """Issue #15: the embedded copy of a refined sequence was normalised once more on load; 1e-16 there grew to
    0.066 mm in the replay and the honest result failed ``verify``."""
    seq = _good()
    rng = np.random.default_rng(3)
    quats = rng.normal(size=(seq.num_frames, 4)).astype(np.float32).astype(np.float64)  # float32-like norms
    seq.object_pose[:, 3:] = quats / np.linalg.norm(quats, axis=1, keepdims=True) * 1.0001
    seq.validate()
    once = seq.object_pose.copy()
    assert np.allclose(np.linalg.norm(once[:, 3:], axis=1), 1.0, atol=1e-15)
    again = sequence_from_npz_bytes(sequence_to_npz_bytes(seq))
    assert np.array_equal(again.object_pose, once)
    assert np.array_equal(sequence_from_npz_bytes(sequence_to_npz_bytes(again)).object_pose, once)
