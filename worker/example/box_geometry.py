"""The built-in example's box and the geometry its grasp is solved and checked with: the box's size and mass,
the solved grasp's record, the box's signed distance and points sampled along the hand's capsules.

Shared by the grasp solver (``grasp_synthesis``), the simulated thumb choice (``grasp_hold``) and the example
sequence (``sequences``), below all three.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import FloatArray
from worker.hand.model import HandGeometry, finger_kinematics

#: Half-extents of the example box (5.6 x 5.6 x 9 cm) and its mass (kg).
BOX_HALF: tuple[float, float, float] = (0.028, 0.028, 0.045)
MASS_KG = 0.2


@dataclass(frozen=True)
class BoxGrasp:
    """Wrist rotation (3,3) and position (3,) in the box frame (origin at the box centre), hinges (45,),
    the open-hand hinges used while approaching, and the final residual norm."""

    wrist_rot: FloatArray
    wrist_pos: FloatArray
    q: FloatArray
    q_open: FloatArray
    cost: float


def box_sdf(points: FloatArray, half: FloatArray) -> FloatArray:
    d = np.abs(points) - half
    return np.asarray(np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(axis=-1), 0.0))


def capsule_samples(geometry: HandGeometry, q: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """For hinges ``q`` (B,45): points (B,5,3,7,3) along every capsule as built in the MJCF (the distal one
    ends one radius short of the tip), their radii (B,5,3,7) and the fingertip keypoints (B,5,3); wrist frame."""
    fk = finger_kinematics(geometry, q)
    b = q.shape[0]
    starts = np.concatenate([np.broadcast_to(geometry.bases[None, :, None, :], (b, 5, 1, 3)), fk.points[:, :, :2]], 2)
    ends = fk.points.copy()
    shorten = np.maximum(geometry.lengths[:, 2] - geometry.radii[:, 2], 0.3 * geometry.lengths[:, 2])
    ends[:, :, 2] = starts[:, :, 2] + (ends[:, :, 2] - starts[:, :, 2]) * (shorten / geometry.lengths[:, 2])[:, None]
    frac = np.linspace(0.0, 1.0, 7)[None, None, None, :, None]
    pts = starts[:, :, :, None, :] + frac * (ends - starts)[:, :, :, None, :]
    radii = np.broadcast_to(geometry.radii[None, :, :, None], pts.shape[:-1])
    return pts, radii, fk.points[:, :, 2]
