"""A robot hand's control coordinates and contact geometry for the refinement (issue #55 item 2).

``robot_basis``: the 10 pose coordinates the CMA-ES moves (``worker.refine.controls.PoseBasis10``, one unit = one
standard deviation) are the principal components of the robot's own retargeted joint motion; where that motion
spans fewer than 10 directions (a grasp-and-lift is mostly one closing motion), the remaining components are the
joints with the widest ranges not yet covered (the PCA of the joint ranges, as a uniform distribution over them
would have), so every coordinate can still move the hand. Each standard deviation is at least ``MIN_STD_FRACTION``
of the joint range it spans, so a direction the recording barely used can still be explored.

``robot_distal``: the fingertip segments the grasp-reach term measures from the object, from the correspondence's
last two keypoints of each finger (DIP and tip), of the description's ``tip_radius``.
"""

from __future__ import annotations

import numpy as np

from common.geometry import FloatArray
from common.sequence import JOINT_NAMES
from worker.robot.reference import RobotReference

#: Pose coordinates per keyframe (``worker.refine.controls.N_POSE``; not imported: the refinement imports this).
N_POSE = 10

#: Floor of a component's standard deviation, as a fraction of the RMS joint range along it.
MIN_STD_FRACTION = 0.05


def robot_basis(ref: RobotReference) -> tuple[FloatArray, FloatArray]:
    """(10, H) components and (10,) standard deviations; see the module docstring."""
    emb = ref.embodiment
    h = emb.num_joints
    span = emb.q_limits[:, 1] - emb.q_limits[:, 0]
    q = ref.q[ref.valid] if ref.valid.sum() >= 2 else ref.q
    _, sing, vt = np.linalg.svd(q - q.mean(axis=0), full_matrices=False)
    std_motion = sing / np.sqrt(max(len(q) - 1, 1))
    keep = [i for i in range(min(N_POSE, len(std_motion))) if std_motion[i] > 1e-3]
    comps = [vt[i] for i in keep]
    stds = [float(std_motion[i]) for i in keep]
    # Complete with joint-range directions orthogonal to what the motion spans, widest range first.
    for j in np.argsort(-span, kind="stable"):
        if len(comps) >= N_POSE:
            break
        e = np.zeros(h)
        e[j] = 1.0
        for c in comps:
            e -= (e @ c) * c
        norm = np.linalg.norm(e)
        if norm > 1e-6:
            comps.append(e / norm)
            stds.append(float(span[j]) / np.sqrt(12.0))  # the std of a uniform distribution over the range
    while len(comps) < N_POSE:  # fewer than 10 joints: zero components move nothing
        comps.append(np.zeros(h))
        stds.append(1.0)
    components = np.asarray(comps, dtype=np.float64)
    std = np.asarray(stds, dtype=np.float64)
    rms_span = np.sqrt(components**2 @ span**2)
    std = np.maximum(std, MIN_STD_FRACTION * np.where(rms_span > 0, rms_span, 1.0))
    return components, std


def robot_distal(ref: RobotReference) -> tuple[tuple[int, ...], tuple[int, ...], float] | None:
    """The distal segments (``worker.refine.losses.DistalSegments``: DIP and tip site indices, radius) of the
    fingers whose DIP (``*3``) and tip (``*4``) the correspondence places, thumb first; None without the thumb's."""
    emb = ref.embodiment
    names = [JOINT_NAMES[k] for k in emb.keypoint_ids]
    dips, tips = [], []
    for finger in ("thumb", "index", "middle", "ring", "pinky"):
        if f"{finger}3" in names and f"{finger}4" in names:
            dips.append(names.index(f"{finger}3"))
            tips.append(names.index(f"{finger}4"))
        elif finger == "thumb":
            return None
    if len(tips) < 2:
        return None
    return tuple(dips), tuple(tips), float(emb.description.tip_radius)
