"""Both ARCTIC loaders on trees the tests write (``tests/support/arctic_tree.py``; the real files may not be copied):
the release layout (``common.arctic_release``: units, field names, the two parts and the joint, MANO hands) and the
dexmachina-processed layout (``common.arctic.load_dexmachina_processed``: joint order, object URDF, limits)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from common.arctic_release import DENSITY_KG_M3, load_arctic_release
from common.errors import UnsupportedFormatError
from common.sequence_io import load_sequence, sequence_from_npz_bytes, sequence_to_npz_bytes
from tests.support.arctic_tree import (
    ANGLES,
    BOTTOM_MM,
    ROTVECS,
    TOP_MM,
    TRANS_MM,
    write_dexmachina_tree,
    write_release_tree,
)


def _corners(bounds: tuple[tuple[float, float], ...]) -> np.ndarray:
    return np.array([[x, y, z] for x in bounds[0] for y in bounds[1] for z in bounds[2]])


def _sorted_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


@pytest.mark.parametrize("split_meshes", [False, True], ids=["mesh+parts.json", "top+bottom.obj"])
def test_release_tree_loads_with_units_fields_and_joint(tmp_path: Path, split_meshes: bool) -> None:
    mano_path = write_release_tree(tmp_path, split_meshes=split_meshes)
    raw = np.load(mano_path, allow_pickle=True).item()
    seq = load_sequence(mano_path)
    assert seq.name == "box_grab_01" and seq.fps == 30.0 and seq.num_frames == 3
    assert seq.meta["source"] == "arctic (release)" and seq.meta["subject"] == "s01" and seq.meta["object"] == "box"
    np.testing.assert_array_equal(seq.up, [0.0, 0.0, 1.0])
    # Object: translation mm -> m, axis-angle -> wxyz, the angle column -> articulation (T, 1).
    np.testing.assert_allclose(seq.object_pose[:, :3], TRANS_MM / 1000.0)
    quat = Rotation.from_rotvec(ROTVECS).as_quat(scalar_first=True)
    np.testing.assert_allclose(np.abs(np.sum(seq.object_pose[:, 3:] * quat, axis=1)), 1.0, atol=1e-12)
    np.testing.assert_array_equal(seq.articulation, ANGLES[:, None])
    obj = seq.object
    assert obj.name == "box" and obj.part_names == ["bottom", "top"] and obj.base_part == "bottom"
    joint = obj.joints[0]
    assert joint.kind == "revolute" and joint.parent == "bottom" and joint.name == "rotation"
    np.testing.assert_array_equal(joint.axis, [0.0, 0.0, -1.0])
    np.testing.assert_array_equal(joint.origin_pos, np.zeros(3))
    np.testing.assert_array_equal(joint.limits, [0.0, 0.6])  # the recording's range, 0 included
    # Parts in metres, each holding its own box.
    bottom, top = obj.part_shapes()
    assert bottom.mesh_vertices is not None and top.mesh_vertices is not None
    assert bottom.mesh_faces is not None and top.mesh_faces is not None
    np.testing.assert_allclose(_sorted_rows(bottom.mesh_vertices), _sorted_rows(_corners(BOTTOM_MM) / 1000.0))
    np.testing.assert_allclose(_sorted_rows(top.mesh_vertices), _sorted_rows(_corners(TOP_MM) / 1000.0))
    assert bottom.mesh_faces.shape == top.mesh_faces.shape == (12, 3)
    assert bottom.mass_kg == pytest.approx(DENSITY_KG_M3 * 0.1 * 0.08 * 0.03)
    assert top.mass_kg == pytest.approx(DENSITY_KG_M3 * ConvexHull(_corners(TOP_MM) / 1000.0).volume)
    # Hands: MANO parameters as ARCTIC stores them (axis-angle, not flat), shape (10,) or per frame.
    for hand in seq.hands:
        src = raw[hand.side]
        m = hand.mano
        assert hand.keypoints is None and m is not None and hand.valid.all()
        assert m.pose_format == "axis_angle" and m.flat_hand_mean is False
        np.testing.assert_array_equal(m.global_orient, src["rot"])
        np.testing.assert_array_equal(m.hand_pose, src["pose"])
        np.testing.assert_array_equal(m.trans, src["trans"])
        np.testing.assert_allclose(m.betas, np.reshape(src["shape"], (-1, 10))[0])
    assert [h.side for h in seq.hands] == ["right", "left"]


def test_release_part_poses_match_arctics_own_formula(tmp_path: Path) -> None:
    """A top vertex in the world: ARCTIC turns it about -z by the angle, then applies the global pose (mm)."""
    seq = load_sequence(write_release_tree(tmp_path))
    top = seq.object.part_shapes()[1]
    assert top.mesh_vertices is not None
    poses = seq.object.part_poses(seq.object_pose, seq.articulation)
    for f in range(3):
        v_mm = top.mesh_vertices * 1000.0
        arctic = Rotation.from_rotvec(ROTVECS[f]).apply(Rotation.from_rotvec(ANGLES[f] * np.array([0, 0, -1.0]))
                                                        .apply(v_mm)) + TRANS_MM[f]  # fmt: skip
        ours = Rotation.from_quat(poses[f, 1, 3:], scalar_first=True).apply(top.mesh_vertices) + poses[f, 1, :3]
        np.testing.assert_allclose(ours * 1000.0, arctic, atol=1e-9)


def test_release_reads_from_either_file_and_a_given_template_folder(tmp_path: Path) -> None:
    mano_path = write_release_tree(tmp_path / "a")
    by_object = load_arctic_release(mano_path.with_name("box_grab_01.object.npy"))
    assert by_object.name == "box_grab_01"
    # The template folder given explicitly (--object-dir), from a tree without meta/.
    other = tmp_path / "b" / "raw_seqs" / "s02"
    other.mkdir(parents=True)
    for suffix in (".mano.npy", ".object.npy"):
        (other / f"box_grab_01{suffix}").write_bytes(mano_path.with_name(f"box_grab_01{suffix}").read_bytes())
    with pytest.raises(UnsupportedFormatError, match="--object-dir"):
        load_sequence(other / "box_grab_01.mano.npy")
    template = tmp_path / "a" / "meta" / "object_vtemplates" / "box"
    seq = load_sequence(other / "box_grab_01.mano.npy", object_dir=template)
    assert seq.meta["subject"] == "s02" and seq.object.part_names == ["bottom", "top"]
    # Saved and read back as a native file, it is the same sequence.
    again = sequence_from_npz_bytes(sequence_to_npz_bytes(seq))
    np.testing.assert_array_equal(again.articulation, seq.articulation)
    assert again.hands[1].mano is not None and again.hands[1].mano.flat_hand_mean is False


def test_release_errors_name_the_file(tmp_path: Path) -> None:
    mano_path = write_release_tree(tmp_path)
    with pytest.raises(UnsupportedFormatError, match=r"box_grab_01\.mano\.npy"):
        load_arctic_release(mano_path.with_name("box_grab_01.smplx.npy"))
    obj_path = mano_path.with_name("box_grab_01.object.npy")
    np.save(obj_path, np.zeros((3, 6)))
    with pytest.raises(UnsupportedFormatError, match=r"box_grab_01\.object\.npy.*\(T, 7\)"):
        load_arctic_release(mano_path)
    obj_path.unlink()
    with pytest.raises(UnsupportedFormatError, match=r"object\.npy is missing"):
        load_arctic_release(mano_path)
    # A hand field of the wrong shape.
    write_release_tree(tmp_path / "c")
    c = tmp_path / "c" / "raw_seqs" / "s01" / "box_grab_01.mano.npy"
    data = np.load(c, allow_pickle=True).item()
    data["left"]["pose"] = data["left"]["pose"][:, :40]
    np.save(c, data, allow_pickle=True)
    with pytest.raises(UnsupportedFormatError, match=r"left\.pose must be \(3, 45\)"):
        load_arctic_release(c)
    # parts.json that does not label every vertex.
    write_release_tree(tmp_path / "d")
    (tmp_path / "d" / "meta" / "object_vtemplates" / "box" / "parts.json").write_text("[0, 1]")
    with pytest.raises(UnsupportedFormatError, match=r"parts\.json"):
        load_arctic_release(tmp_path / "d" / "raw_seqs" / "s01" / "box_grab_01.mano.npy")


def test_release_pickle_runs_no_code(tmp_path: Path) -> None:
    """A ``.mano.npy`` whose pickle names any global but NumPy's array machinery is refused before it runs."""
    mano_path = write_release_tree(tmp_path)
    np.save(mano_path, np.array({"right": Path("/")}, dtype=object), allow_pickle=True)
    with pytest.raises(UnsupportedFormatError, match="refuses to load"):
        load_arctic_release(mano_path)


#: MANO's joint order (16 joints, then the tips) for each of ``common.sequence.JOINT_NAMES``: the wrist; thumb
#: 13-15 + tip 16; index 1-3 + 17; middle 4-6 + 18; ring 10-12 + 19; pinky 7-9 + 20.
EXPECTED_ORDER = [0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20]


def test_dexmachina_tree_loads(tmp_path: Path) -> None:
    path, joints = write_dexmachina_tree(tmp_path)
    seq = load_sequence(path)
    assert seq.name == "box_use_01" and seq.fps == 30.0 and seq.meta["subject"] == "s01"
    for hand in seq.hands:
        assert hand.mano is None and hand.valid.all()
        np.testing.assert_array_equal(hand.keypoints, joints[hand.side][:, EXPECTED_ORDER])
    np.testing.assert_allclose(seq.object_pose[:, :3], TRANS_MM / 1000.0)
    np.testing.assert_array_equal(seq.articulation, ANGLES[:, None])
    obj = seq.object
    assert obj.name == "box" and obj.part_names == ["bottom", "top"]
    assert obj.mass_kg == 0.9 and obj.parts[0].shape.mass_kg == 0.15
    assert obj.parts[0].shape.mesh_vertices is not None
    np.testing.assert_allclose(_sorted_rows(obj.parts[0].shape.mesh_vertices), _sorted_rows(_corners(TOP_MM) / 1e3))
    joint = obj.joints[0]
    np.testing.assert_array_equal(joint.axis, [0.0, 0.0, -1.0])
    # The URDF says [0, 0.5]; the recording reaches 0.6: widened, and said so.
    np.testing.assert_allclose(joint.limits, [0.0, 0.6])
    assert seq.meta["limits_widened.rotation"] == "[0, 0.5] -> [0, 0.6]"


def test_dexmachina_object_folder_given_or_missing(tmp_path: Path) -> None:
    path, _ = write_dexmachina_tree(tmp_path)
    moved = tmp_path / "elsewhere"
    (tmp_path / "arctic" / "box").rename(moved)
    with pytest.raises(UnsupportedFormatError, match="--object-dir"):
        load_sequence(path)
    assert load_sequence(path, object_dir=moved).object.part_names == ["bottom", "top"]
