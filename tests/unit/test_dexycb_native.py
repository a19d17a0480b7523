"""DexYCB native layout: a tiny tree built here (2 sequences, 6 frames, a cube, a known table frame)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from common.dexycb_native import load_dexycb_native, object_poses, ycb_masses
from common.errors import ManoModelMissingError, SequenceValidationError
from common.sequence_io import load_sequence
from common.settings import get_settings

T = 6
HALF = 0.04  # cube half-size (m)
SUBJECT = "20200709-subject-01"
BETAS = [0.5, -0.3, 0.1, 0.0, 0.2, -0.1, 0.05, 0.0, 0.0, 0.01]


def _master_from_table() -> np.ndarray:
    """A camera looking down at the table: table +z maps to a camera direction with -y (up in OpenCV)."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("xyz", [-125.0, 5.0, 10.0], degrees=True).as_matrix()
    out[:3, 3] = [0.1, 0.3, 0.9]
    return out


def _write_cube(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    corners = [(x, y, z) for x in (-HALF, HALF) for y in (-HALF, HALF) for z in (-HALF, HALF)]
    faces = [(1, 3, 2), (1, 2, 5), (1, 5, 3), (8, 6, 7), (8, 7, 4), (8, 4, 6),
             (2, 4, 3), (2, 6, 4), (5, 7, 6), (5, 6, 2), (3, 7, 5), (3, 4, 7)]  # fmt: skip
    lines = [f"v {x} {y} {z}" for x, y, z in corners] + [f"f {a} {b} {c}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def _object_track(master_from_table: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """Cube resting on the table at frame 0 (rotated 30 deg about table z), then lifted 1 cm a frame."""
    rot_table = Rotation.from_euler("z", 30, degrees=True)
    rot_cam = Rotation.from_matrix(master_from_table[:3, :3]) * rot_table
    pos_table = np.array([[0.3, 0.2, HALF + 0.01 * i] for i in range(T)])
    pos_cam = pos_table @ master_from_table[:3, :3].T + master_from_table[:3, 3]
    return pos_cam, rot_cam


def _write_tree(root: Path) -> dict[str, Path]:
    m = _master_from_table()
    cal = root / "calibration"
    (cal / "extrinsics_20200702_151821").mkdir(parents=True)
    (cal / "extrinsics_20200702_151821" / "extrinsics.yml").write_text(
        yaml.safe_dump(
            {
                "master": "840412060917",
                "extrinsics": {
                    "840412060917": [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0],
                    "apriltag": m[:3].ravel().tolist(),
                },
            }
        )
    )
    for calib in ("20200709_right", "20200709_left"):
        (cal / f"mano_{calib}").mkdir(parents=True)
        (cal / f"mano_{calib}" / "mano.yml").write_text(yaml.safe_dump({"betas": BETAS}))
    _write_cube(root / "models" / "010_potted_meat_can" / "textured_simple.obj")

    pos_cam, rot_cam = _object_track(m)
    rng = np.random.default_rng(0)
    dirs = {}
    # Sequence 1: right hand, two objects (grasp the second), toolkit pose_y layout, master labels.
    s1 = root / SUBJECT / "20200709_141754"
    s1.mkdir(parents=True)
    pose_y = np.zeros((T, 2, 7), np.float32)
    pose_y[:, 0] = [0, 0, 0, 1, 0.5, 0.5, 0.5]
    pose_y[:, 1, :4] = rot_cam.as_quat()  # x y z w
    pose_y[:, 1, 4:] = pos_cam
    pose_m = rng.normal(0, 0.1, (T, 1, 51)).astype(np.float32)
    pose_m[:2] = 0.0  # hand not yet in view
    np.savez(s1 / "pose.npz", pose_y=pose_y, pose_m=pose_m)
    meta = {
        "serials": ["836212060125", "840412060917"], "num_frames": T, "ycb_ids": [1, 9], "ycb_grasp_ind": 1,
        "mano_sides": ["right"], "mano_calib": ["20200709_right"], "extrinsics": "20200702_151821",
    }  # fmt: skip
    (s1 / "meta.yml").write_text(yaml.safe_dump(meta))
    (s1 / "840412060917").mkdir()
    joints = pos_cam[:, None, None, :] + rng.normal(0, 0.05, (T, 1, 21, 3))
    joints[:2] = -1.0  # the toolkit's marker for "no hand"
    for i in range(T):
        np.savez(s1 / "840412060917" / f"labels_{i:06d}.npz", joint_3d=joints[i].astype(np.float32))
    dirs["s1"] = s1
    # Sequence 2: both hands, [R|t] pose_y layout, no labels (MANO only).
    s2 = root / SUBJECT / "20200709_141841"
    s2.mkdir(parents=True)
    mats = np.zeros((T, 1, 3, 4), np.float32)
    mats[:, 0, :, :3] = rot_cam.as_matrix()
    mats[:, 0, :, 3] = pos_cam
    pose_m2 = rng.normal(0, 0.1, (T, 2, 51)).astype(np.float32)
    pose_m2[4:, 1] = 0.0  # left hand leaves
    np.savez(s2 / "pose.npz", pose_y=mats, pose_m=pose_m2)
    meta2 = dict(meta, ycb_ids=[9], ycb_grasp_ind=0, mano_sides=["right", "left"],
                 mano_calib=["20200709_right", "20200709_left"])  # fmt: skip
    (s2 / "meta.yml").write_text(yaml.safe_dump(meta2))
    dirs["s2"] = s2
    return dirs


@pytest.fixture()
def tree(tmp_path: Path) -> dict[str, Path]:
    return _write_tree(tmp_path / "dexycb")


def test_world_frame_object_and_hand(tree: dict[str, Path]) -> None:
    seq = load_sequence(tree["s1"])
    np.testing.assert_allclose(seq.world_transform(), np.linalg.inv(_master_from_table()), atol=1e-6)
    assert seq.object.name == "010_potted_meat_can"
    assert seq.object.mass_kg == pytest.approx(ycb_masses()["010_potted_meat_can"]) == pytest.approx(0.37)
    world = seq.object_pose_world()
    # The cube rests on the table (its centre HALF above z = 0), then rises 1 cm a frame.
    np.testing.assert_allclose(world[:, 2], HALF + 0.01 * np.arange(T), atol=1e-5)
    np.testing.assert_allclose(world[:, :2], np.tile([0.3, 0.2], (T, 1)), atol=1e-5)
    # Quaternion order: x y z w in pose.npz -> w x y z here; world rotation is 30 deg about +z.
    yaw = Rotation.from_quat(world[:, 3:], scalar_first=True).as_euler("xyz", degrees=True)
    np.testing.assert_allclose(yaw, np.tile([0.0, 0.0, 30.0], (T, 1)), atol=1e-3)
    low = seq.object.surface_vertices() @ Rotation.from_quat(world[0, 3:], scalar_first=True).as_matrix().T
    assert (low[:, 2] + world[0, 2]).min() == pytest.approx(0.0, abs=1e-5)

    (hand,) = seq.hands
    assert hand.side == "right"
    np.testing.assert_array_equal(hand.valid, [False, False, True, True, True, True])
    assert hand.keypoints is not None and np.all(hand.keypoints[:2] == 0.0)
    assert hand.mano is not None and hand.mano.pose_format == "pca" and not hand.mano.flat_hand_mean
    np.testing.assert_allclose(hand.mano.betas, BETAS)
    assert hand.mano.hand_pose.shape == (T, 45)
    assert seq.name == f"{SUBJECT}__20200709_141754" and seq.fps == 30.0


def test_two_hands_without_labels_need_mano(tree: dict[str, Path], tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    monkeypatch.delenv("HOI_REFINE_MANO_DIR", raising=False)
    get_settings.cache_clear()
    with pytest.raises(ManoModelMissingError, match=r"HOI_REFINE_MANO_DIR.*not set"):
        load_dexycb_native(tree["s2"])
    mano_dir = tmp_path / "mano"
    mano_dir.mkdir()
    (mano_dir / "MANO_RIGHT.pkl").write_bytes(b"x")
    monkeypatch.setenv("HOI_REFINE_MANO_DIR", str(mano_dir))
    get_settings.cache_clear()
    with pytest.raises(ManoModelMissingError, match=r"MANO_LEFT\.pkl"):
        load_dexycb_native(tree["s2"] / "meta.yml")
    (mano_dir / "MANO_LEFT.pkl").write_bytes(b"x")
    seq = load_dexycb_native(tree["s2"] / "meta.yml")
    assert [h.side for h in seq.hands] == ["right", "left"]
    assert all(h.keypoints is None and h.mano is not None for h in seq.hands)
    np.testing.assert_array_equal(seq.hands[1].valid, [True] * 4 + [False] * 2)
    # (T, n, 3, 4) poses decode to the same world track as sequence 1's quaternions.
    np.testing.assert_allclose(seq.object_pose_world()[:, 2], HALF + 0.01 * np.arange(T), atol=1e-5)


def test_object_poses_fill_invalid_frames() -> None:
    pose_y = np.zeros((4, 1, 7))
    pose_y[:, 0] = [0, 0, 0, 1, 0, 0, 0]  # the toolkit's "no pose" row
    pose_y[2, 0] = [0, 0, np.sin(0.3), np.cos(0.3), 0.1, 0.2, 0.3]
    poses, valid = object_poses(pose_y, 0)
    np.testing.assert_array_equal(valid, [False, False, True, False])
    np.testing.assert_allclose(poses, np.tile([0.1, 0.2, 0.3, np.cos(0.3), 0, 0, np.sin(0.3)], (4, 1)))


def test_bad_inputs_name_the_field(tree: dict[str, Path]) -> None:
    meta = yaml.safe_load((tree["s1"] / "meta.yml").read_text())
    (tree["s1"] / "meta.yml").write_text(yaml.safe_dump(dict(meta, ycb_ids=[1, 19])))
    with pytest.raises(SequenceValidationError, match="051_large_clamp"):
        load_dexycb_native(tree["s1"])
    (tree["s1"] / "meta.yml").write_text(yaml.safe_dump(dict(meta, num_frames=T + 1)))
    with pytest.raises(SequenceValidationError, match="num_frames"):
        load_dexycb_native(tree["s1"])
