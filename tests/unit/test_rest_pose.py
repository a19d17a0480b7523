"""The object's start pose averaged over the frames before a hand comes near (worker.simulation.rest_pose)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from common.geometry import rotation_angle
from worker.simulation.rest_pose import approach_frame, mean_pose, moved_frame, rest_pose

# A 2 x 2 x 2 cm cube's corners and face centres: the object surface.
SURFACE = np.array([[x, y, z] for x in (-0.01, 0.01) for y in (-0.01, 0.01) for z in (-0.01, 0.01)]
                   + [[0.01, 0, 0], [-0.01, 0, 0], [0, 0.01, 0], [0, -0.01, 0], [0, 0, 0.01], [0, 0, -0.01]])


def _wxyz(rot: Rotation) -> np.ndarray:
    return np.asarray(rot.as_quat())[..., [3, 0, 1, 2]]


def _track(angles_deg: np.ndarray, pos: tuple[float, float, float] = (0.3, 0.1, 0.01)) -> np.ndarray:
    """(T, 7) poses turning about z by the given angles at a fixed position."""
    quats = _wxyz(Rotation.from_euler("z", np.asarray(angles_deg)[:, None], degrees=True))
    return np.concatenate([np.tile(pos, (len(angles_deg), 1)), quats], axis=1)


def _hand_closing_in(t: int, arrive: int, target: np.ndarray) -> np.ndarray:
    """(T, 21, 3) keypoints 30 cm above ``target`` that reach it (all 21 at one point) at frame ``arrive``."""
    height = np.clip(0.3 * (arrive - np.arange(t)) / arrive, 0.0, None)
    kp = np.tile(target, (t, 21, 1)).astype(np.float64)
    kp[:, :, 2] += height[:, None]
    return kp


def test_the_mean_rotation_ignores_the_quaternion_sign_and_lies_between_the_samples() -> None:
    poses = _track(np.array([-4.0, -2.0, 0.0, 2.0, 4.0]))
    poses[1, 3:] *= -1  # the same rotation, the other sign
    poses[:, :3] += np.array([[0.001], [-0.001], [0.0], [0.002], [-0.002]])
    mean = mean_pose(poses)
    np.testing.assert_allclose(mean[3:], [1, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(mean[:3], [0.3, 0.1, 0.01], atol=1e-12)


def test_the_mean_keeps_the_sign_of_the_first_frame() -> None:
    poses = _track(np.array([170.0, 175.0, 180.0]))
    mean = mean_pose(poses)
    assert mean[3:] @ poses[0, 3:] > 0
    assert np.degrees(rotation_angle(mean[3:], _wxyz(Rotation.from_euler("z", 175, degrees=True)))) < 1e-6


def test_the_approach_is_the_first_frame_a_keypoint_is_within_the_distance_of_the_surface() -> None:
    t = 40
    poses = _track(np.zeros(t))
    top = np.array([0.3, 0.1, 0.02])  # the cube's top face centre, world
    hand = _hand_closing_in(t, arrive=30, target=top)
    # height at frame f: 0.3 (30 - f) / 30 m = (30 - f) cm; within 2.5 cm from f = 28 on.
    assert approach_frame(poses, SURFACE, [hand], 0.025) == 28
    assert approach_frame(poses, SURFACE, [hand + np.array([0.0, 0.0, 1.0])], 0.025) == t  # never comes near
    # Two hands: the earlier one decides (1.5 (20 - f) cm: within 2.5 cm from f = 19 on).
    assert approach_frame(poses, SURFACE, [hand, _hand_closing_in(t, arrive=20, target=top)], 0.025) == 19


def test_the_rest_pose_is_the_mean_before_the_approach_only() -> None:
    t = 40
    angles = np.r_[np.linspace(0.0, 6.0, 28), np.full(t - 28, 60.0)]  # drifts 6 degrees, then the hand turns it
    poses = _track(angles)
    hand = _hand_closing_in(t, arrive=30, target=np.array([0.3, 0.1, 0.02]))  # within 2.5 cm from frame 28
    rest = rest_pose(poses, SURFACE, [hand], 0.025)
    expected = _wxyz(Rotation.from_euler("z", 3.0, degrees=True))
    assert np.degrees(rotation_angle(rest[3:], expected)) < 0.01
    # A hand already at the object at frame 0, or the averaging switched off: frame 0 as recorded.
    np.testing.assert_array_equal(rest_pose(poses, SURFACE, [hand[29:30].repeat(t, 0)], 0.025), poses[0])
    np.testing.assert_array_equal(rest_pose(poses, SURFACE, [hand], 0.0), poses[0])


def test_the_rest_phase_ends_where_the_recorded_object_moves_even_before_the_hand_is_near() -> None:
    """A hand tracked 5 cm off: the object is pushed (moves 1 cm per frame from frame 10) while the recorded hand
    is still far. The mean must not take in the moving frames."""
    t = 30
    poses = _track(np.zeros(t))
    poses[10:, 0] += 0.01 * np.arange(1, t - 9)
    assert moved_frame(poses) == 10
    hand = _hand_closing_in(t, arrive=25, target=np.array([0.3, 0.1, 0.02]))
    rest = rest_pose(poses, SURFACE, [hand], 0.025)
    np.testing.assert_allclose(rest, poses[0], atol=1e-12)
    # Jitter within the noise bounds does not end it.
    jitter = _track(np.tile([3.0, -3.0], t // 2))
    jitter[:, 0] += np.tile([0.002, -0.002], t // 2)
    assert moved_frame(jitter) == t
