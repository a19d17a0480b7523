"""JSON sequence parsing: malformed numbers become field-named problems, never crashes."""

from __future__ import annotations

import warnings
from typing import Any

import pytest

from common.errors import SequenceValidationError
from common.sequence_io import sequence_from_json_dict


def _doc(size: Any) -> dict[str, Any]:
    return {
        "fps": 30,
        "object": {"mass_kg": 1.0, "primitive": {"kind": "box", "size": size}},
        "object_pose": [[0, 0, 0, 1, 0, 0, 0]] * 2,  # two frames: the shortest sequence (MIN_FRAMES)
        "hands": [{"side": "right", "valid": [True] * 2, "keypoints": [[[0.0, 0.0, 0.0]] * 21] * 2}],
    }


@pytest.mark.parametrize("size", [[10**400, 1, 1], [[1, 2], [3]], ["a", 1, 1]])
def test_unparseable_numbers_name_the_field(size: Any) -> None:
    with pytest.raises(SequenceValidationError) as info:
        sequence_from_json_dict(_doc(size))
    fields = [p.field for p in info.value.problems]
    assert fields == ["object.primitive.size"], fields


def test_missing_size_is_required() -> None:
    doc = _doc(None)
    del doc["object"]["primitive"]["size"]
    with pytest.raises(SequenceValidationError, match=r"object\.primitive\.size: is required"):
        sequence_from_json_dict(doc)


def test_valid_document_parses() -> None:
    seq = sequence_from_json_dict(_doc([0.05, 0.05, 0.05]))
    assert seq.num_frames == 2 and seq.object.primitive == "box"


def test_huge_world_transform_is_rejected_without_overflow() -> None:
    doc = _doc([0.05, 0.05, 0.05])
    doc["world_from_camera"] = [[1e300, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow RuntimeWarning would fail the test
        with pytest.raises(SequenceValidationError, match="world_from_camera"):
            sequence_from_json_dict(doc)
