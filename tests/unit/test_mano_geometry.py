"""The MANO hand in the built-in hand's terms: rest geometry, part hulls, hinge conversion (no torch)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from worker.hand.mano.hand_geometry import hinges_to_rotations, mano_hand_geometry, rotations_to_hinges
from worker.hand.mano.synthetic_model import skeleton
from worker.hand.model import forward_keypoints, wrist_frames


@pytest.mark.parametrize("side", ["right", "left"])
def test_rest_pose_reproduces_keypoints(mano_dir: Path, side: str) -> None:
    mgeo = mano_hand_geometry(mano_dir, side, np.zeros(10))  # type: ignore[arg-type]
    joints, tips = skeleton()
    mirror = np.array([1, -1, 1]) if side == "left" else 1
    np.testing.assert_allclose(mgeo.joints, joints * mirror, atol=1e-12)
    np.testing.assert_allclose(mgeo.keypoints[[4, 8, 12, 16, 20]], tips * mirror, atol=1e-12)
    # Zero MANO rotations -> hinge angles that put the built-in hand exactly on MANO's (curled) rest pose.
    q = rotations_to_hinges(np.tile(np.eye(3), (1, 16, 1, 1)), mgeo)
    assert np.abs(q).max() > 0.05  # the template's rest curl lives in the hinges
    quat = Rotation.from_matrix(mgeo.wrist_frame).as_quat(scalar_first=True)
    kp = forward_keypoints(mgeo.geometry, mgeo.wrist_origin, quat, q[0])
    np.testing.assert_allclose(kp, mgeo.keypoints, atol=1e-9)
    np.testing.assert_allclose(mgeo.wrist_frame, wrist_frames(mgeo.keypoints[None], side)[0])  # type: ignore[arg-type]


def test_hinge_conversion_inverts(mano_dir: Path) -> None:
    mgeo = mano_hand_geometry(mano_dir, "right", np.zeros(10))
    rng = np.random.default_rng(1)
    rot = Rotation.from_rotvec(rng.normal(0, 0.5, (7 * 16, 3))).as_matrix().reshape(7, 16, 3, 3)
    q = rotations_to_hinges(rot, mgeo)
    np.testing.assert_allclose(hinges_to_rotations(q, mgeo), rot[:, 1:], atol=1e-10)
    # A pure flexion of the index MCP about the segment's -y axis is read as flexion only.
    rest = rotations_to_hinges(np.tile(np.eye(3), (1, 16, 1, 1)), mgeo)[0]
    s = mgeo.segment_frames[1, 0]
    bend = np.tile(np.eye(3), (1, 16, 1, 1))
    bend[0, 1] = Rotation.from_rotvec(0.7 * (s @ [0, -1.0, 0])).as_matrix()
    delta = rotations_to_hinges(bend, mgeo)[0] - rest
    expected = np.zeros(45)
    expected[9 + 1] = 0.7  # index (finger 1), joint 1, flex
    np.testing.assert_allclose(delta, expected, atol=1e-9)


def test_betas_and_part_hulls(mano_dir: Path) -> None:
    base = mano_hand_geometry(mano_dir, "right", np.zeros(10))
    big = mano_hand_geometry(mano_dir, "right", np.array([1.0] + [0.0] * 9))
    # beta 0 of the test model scales the hand by 4 % about the wrist.
    assert big.geometry.hand_length == pytest.approx(1.04 * base.geometry.hand_length, rel=1e-9)
    names = [h.name for h in base.hulls]
    assert names[0] == "palm" and len(names) == 16 and len(set(names)) == 16
    assert sorted(h.mano_joint for h in base.hulls) == list(range(16))
    for hull in base.hulls[1:]:
        f, j = divmod(base.hulls.index(hull) - 1, 3)
        v = hull.vertices
        # In its segment frame a part starts at the joint and runs along +x for about its bone length.
        assert v[:, 0].min() > -0.012 and v[:, 0].max() == pytest.approx(base.geometry.lengths[f, j], rel=0.2)
        assert np.linalg.norm(v[:, 1:], axis=1).max() < 0.015
        assert hull.faces.max() < len(v) and hull.faces.shape[1] == 3
    # The palm lies in the wrist frame between wrist and knuckles, thin along the palm normal (z).
    palm = base.hulls[0].vertices
    assert palm[:, 0].min() > -0.01 and palm[:, 0].max() < 0.1 and np.ptp(palm[:, 2]) < 0.04
