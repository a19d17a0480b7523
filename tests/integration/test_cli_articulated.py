"""Articulated sequences on the command line (issue #52): ``inspect`` shows the parts, joints and the recorded
articulation; bad articulated files (NPZ and JSON) are one-line errors naming the field, exit 2; ``--object-dir``
finds an ARCTIC object elsewhere."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest

from common.cli import main
from common.npz_writer import deterministic_npz_bytes
from common.sequence_io import save_sequence, sequence_to_json_dict, sequence_to_npz_bytes
from tests.support.arctic_tree import write_dexmachina_tree
from tests.support.articulated import drawer_cabinet_sequence, tiny_articulated_sequence


def test_inspect_shows_parts_joints_and_the_recorded_range(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "cabinet.json"
    save_sequence(drawer_cabinet_sequence().validate(), path)
    assert main(["inspect", str(path)]) == 0
    out = " ".join(capsys.readouterr().out.split())  # rich wraps long cells
    assert "base part cabinet" in out and "parts" in out and "cabinet (base), door, drawer, knob0" in out
    assert "joint drawer_slide" in out and "prismatic, cabinet -> drawer" in out and "limits [0, 0.25] m" in out
    assert "articulation door_hinge" in out and "recorded 0 to 1.2 rad (0.0 to 68.8 deg" in out
    assert "articulation drawer_slide" in out and "(0.0 to 20.0 cm" in out
    assert "joint knob0_turn" in out and "drawer -> knob0" in out


def _npz_with(**changes: object) -> bytes:
    with np.load(io.BytesIO(sequence_to_npz_bytes(tiny_articulated_sequence().validate()))) as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update(changes)
    return deterministic_npz_bytes(arrays)


def _json_with(edit: object) -> bytes:
    doc = sequence_to_json_dict(tiny_articulated_sequence().validate())
    edit(doc)  # type: ignore[operator]
    return json.dumps(doc).encode()


CASES = [
    ("axis.npz", lambda: _npz_with(object_joint_axes=np.zeros((1, 3))), "object.parts[0].joint.axis"),
    ("limits.npz", lambda: _npz_with(object_articulation=np.full((5, 1), -0.5)), "articulation"),
    ("parent.npz", lambda: _npz_with(object_joint_parents=np.array(["nowhere"])), "object.parts[0].joint.parent"),
    ("shape.npz", lambda: _npz_with(object_articulation=np.zeros((5, 3))), "object_articulation"),
    ("axis.json", lambda: _json_with(lambda d: d["object"]["parts"][0]["joint"].__setitem__("axis", [0, 0, 0])),
     "object.parts[0].joint.axis"),
    ("mesh.json", lambda: _json_with(lambda d: d["object"]["parts"][0].pop("primitive")), "object.parts[0]"),
    ("shape.json", lambda: _json_with(lambda d: d.__setitem__("articulation", [[0.1]] * 4)), "articulation"),
]


@pytest.mark.parametrize("name, make, field", CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("command", ["inspect", "replay"])
def test_bad_articulated_files_are_one_line_errors(
    command: str, name: str, make: object, field: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / name
    path.write_bytes(make())  # type: ignore[operator]
    assert main([command, str(path)]) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hoi-refine: error: ") and field in lines[0], err


def test_object_dir_finds_a_dexmachina_object(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = write_dexmachina_tree(tmp_path)
    moved = tmp_path / "objects" / "box"
    moved.parent.mkdir()
    (tmp_path / "arctic" / "box").rename(moved)
    assert main(["inspect", str(path)]) == 2
    assert "--object-dir" in capsys.readouterr().err
    assert main(["inspect", str(path), "--object-dir", str(moved)]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "joint rotation" in out and "bottom -> top" in out and "recorded 0 to 0.6 rad" in out
