"""The hand: the built-in articulated MANO-topology hand (palm + 15 segments, 45 hinges; DESIGN §1.1), the
reference it is driven along, keypoint retargeting by IK (§1.2), the packaged pose basis (§1.3) and the
optional MANO model (``mano``). Kinematics only: NumPy and SciPy, no MuJoCo (its MJCF is built by
``worker.simulation``).
"""

from worker.hand.model import (
    HINGE_NAMES,
    JOINT_LIMITS,
    JOINT_LOWER,
    JOINT_UPPER,
    HandGeometry,
    default_geometry,
    fit_hand_geometry,
    forward_keypoints,
)
from worker.hand.pose_basis import PoseBasis, load_pose_basis
from worker.hand.reference import HandReference
from worker.hand.retarget import retarget_hand, retarget_keypoints, retarget_sequence

__all__ = [
    "HINGE_NAMES",
    "JOINT_LIMITS",
    "JOINT_LOWER",
    "JOINT_UPPER",
    "HandGeometry",
    "HandReference",
    "PoseBasis",
    "default_geometry",
    "fit_hand_geometry",
    "forward_keypoints",
    "load_pose_basis",
    "retarget_hand",
    "retarget_keypoints",
    "retarget_sequence",
]
