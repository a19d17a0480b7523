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
from tests.support.dexycb_tree import BETAS, HALF, SUBJECT, T, master_from_table, write_tree


@pytest.fixture()
def tree(tmp_path: Path) -> dict[str, Path]:
    return write_tree(tmp_path / "dexycb")


def test_world_frame_object_and_hand(tree: dict[str, Path]) -> None:
    seq = load_sequence(tree["s1"])
    np.testing.assert_allclose(seq.world_transform(), np.linalg.inv(master_from_table()), atol=1e-6)
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
