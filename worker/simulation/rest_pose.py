"""The object's start pose: its recorded poses averaged over the frames before a hand comes near.

Every DexYCB-style sequence starts with the object at rest, and nothing moves it until a hand touches it. The
recording still moves it: each frame's pose is a separate vision estimate, off by a degree or two and a
millimetre, and for a body symmetric about an axis (a marker, a can) the turn about that axis is barely observed
and can drift several degrees while the hand is still 10 cm away. The simulated object cannot follow any of that
(it must move only through contact), so its start pose is what its error over the whole approach is measured
against. Frame 0 alone is one noisy sample of the rest pose; the mean over every frame before a hand keypoint
first comes within ``approach_m`` of the object's surface (and before its recorded pose leaves frame 0's by
more than noise, ``moved_frame``) is a better estimate of it, and it is the pose that minimises the (squared)
error over those frames.
"""

from __future__ import annotations

from collections.abc import Sequence as Seq

import numpy as np
from scipy.spatial import cKDTree

from common.geometry import FloatArray, quat_to_matrix, rotation_error_deg

#: Beyond these from frame 0 the recorded object has moved, not jittered: vision noise of a resting DexYCB object
#: stays within 3 mm, and its turn about a symmetry axis within 8 degrees, before a hand comes near.
MAX_SHIFT_M = 0.005
MAX_TURN_DEG = 10.0


def approach_frame(
    object_pose: FloatArray, surface_points: FloatArray, hand_keypoints: Seq[FloatArray], approach_m: float
) -> int:
    """First frame where any hand keypoint is within ``approach_m`` of the object surface (T if never).

    ``object_pose`` (T, 7) world pos + wxyz quat; ``surface_points`` (N, 3) object frame; ``hand_keypoints``
    one (T, K, 3) world array per hand.
    """
    t = object_pose.shape[0]
    tree = cKDTree(surface_points)
    first = t
    for kp in hand_keypoints:
        local = _to_object_frame(object_pose, kp)
        dist, _ = tree.query(local.reshape(-1, 3))
        near = np.nonzero(dist.reshape(t, -1).min(axis=1) < approach_m)[0]
        if near.size:
            first = min(first, int(near[0]))
    return first


def mean_pose(poses: FloatArray) -> FloatArray:
    """(7,) mean of (N, 7) poses: the mean position and the chordal L2 mean rotation (the dominant eigenvector
    of the quaternions' scatter matrix, so q and -q count alike)."""
    quats = poses[:, 3:] / np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(quats.T @ quats)
    q = vecs[:, -1]
    if q @ quats[0] < 0:  # the sign closest to the first frame's
        q = -q
    return np.concatenate([poses[:, :3].mean(axis=0), q])


def rest_pose(
    object_pose: FloatArray, surface_points: FloatArray, hand_keypoints: Seq[FloatArray], approach_m: float
) -> FloatArray:
    """(7,) the object's start pose (see the module docstring); frame 0 as recorded when a hand is already near
    it at frame 0 or ``approach_m`` <= 0."""
    if approach_m <= 0:
        return np.asarray(object_pose[0], dtype=np.float64).copy()
    return mean_pose(object_pose[: max(resting_frames(object_pose, surface_points, hand_keypoints, approach_m), 1)])


def resting_frames(
    object_pose: FloatArray, surface_points: FloatArray, hand_keypoints: Seq[FloatArray], approach_m: float
) -> int:
    """How many frames the object rests untouched in the recording: those before a hand keypoint first comes
    within ``approach_m`` of its surface and before it moves (``moved_frame``); 0 when ``approach_m`` <= 0."""
    if approach_m <= 0:
        return 0
    return min(approach_frame(object_pose, surface_points, hand_keypoints, approach_m), moved_frame(object_pose))


def moved_frame(object_pose: FloatArray, max_shift_m: float = MAX_SHIFT_M, max_turn_deg: float = MAX_TURN_DEG) -> int:
    """First frame whose recorded pose is more than ``max_shift_m`` or ``max_turn_deg`` from frame 0 (T if none):
    past that the object is moving, whatever the hand track says (a hand tracked a few centimetres off reaches
    the object in the recording after the object has started to move)."""
    shift = np.linalg.norm(object_pose[:, :3] - object_pose[0, :3], axis=1)
    turn = rotation_error_deg(object_pose[:, 3:], object_pose[:1, 3:])
    moved = np.nonzero((shift > max_shift_m) | (turn > max_turn_deg))[0]
    return int(moved[0]) if moved.size else object_pose.shape[0]


def _to_object_frame(object_pose: FloatArray, points: FloatArray) -> FloatArray:
    """(T, K, 3) world points -> each frame's object frame."""
    rots = np.stack([quat_to_matrix(q) for q in object_pose[:, 3:]])  # (T, 3, 3) world_from_object
    return np.asarray(np.einsum("tji,tkj->tki", rots, points - object_pose[:, None, :3]), dtype=np.float64)
