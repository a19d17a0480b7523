"""Reference retargeting (DESIGN §1.2): keypoints -> wrist pose + 45 hinge angles per frame.

Per frame: the wrist pose is the rigid (Kabsch) alignment of the fitted palm points onto the observed ones
(palm keypoints are rigid in MANO, so this is exact up to noise); the fingers are then solved in the wrist
frame by damped least squares (Levenberg-Marquardt), all 5 fingers at once, within the joint limits,
warm-started from the previous frame. Hinges the keypoints determine poorly (twists, distal abductions:
``hand_model.PRIMARY_HINGES`` is False) are pulled gently towards neutral so the solution is unique.
Frames without a valid hand are interpolated (wrist: slerp; hinges: linear; constant beyond the ends).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

from common.errors import SequenceValidationError
from common.geometry import FloatArray, cross
from common.sequence import HandTrack, Sequence, Side
from worker.hand.mano import mano_available, mano_model_path
from worker.hand.mano.pose import mano_reference
from worker.hand.model import (
    FINGER_BASE_KEYPOINT,
    JOINT_LOWER,
    JOINT_UPPER,
    PALM_KEYPOINTS,
    PRIMARY_HINGES,
    HandGeometry,
    finger_kinematics,
    fit_hand_geometry,
    forward_keypoints,
)
from worker.hand.reference import HandReference

#: LM damping (m²) and the pull of secondary hinges towards neutral (m²/rad² — a 1 cm error outweighs
#: ~0.7 rad of secondary angle); iterations per frame and convergence threshold (rad).
IK_DAMPING = 1e-6
IK_SECONDARY_WEIGHT = 2e-4
IK_MAX_ITERATIONS = 30
IK_TOLERANCE = 1e-7
_FIRST_FRAME_ITERATIONS = 100


def kabsch(template: FloatArray, observed: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Batched rigid fit: R (T,3,3), t (T,3) minimising ||R template + t - observed|| for ``observed`` (T,N,3)."""
    if template.ndim != 2 or observed.ndim != 3 or observed.shape[1:] != template.shape:
        raise ValueError(f"template (N,3) and observed (T,N,3) expected, got {template.shape}, {observed.shape}")
    pc = template - template.mean(axis=0)
    oc_mean = observed.mean(axis=1)
    oc = observed - oc_mean[:, None]
    h = np.einsum("ni,tnj->tij", pc, oc)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.swapaxes(vt, 1, 2) @ np.swapaxes(u, 1, 2)))
    fix = np.ones((len(d), 3))
    fix[:, 2] = d
    rot = np.swapaxes(vt, 1, 2) @ (fix[:, :, None] * np.swapaxes(u, 1, 2))
    t = oc_mean - np.einsum("tij,j->ti", rot, template.mean(axis=0))
    return rot, t


def solve_fingers(
    geometry: HandGeometry, targets: FloatArray, q_init: FloatArray, max_iterations: int = IK_MAX_ITERATIONS
) -> FloatArray:
    """Damped least squares for the 5 fingers of one frame, in the wrist frame.

    ``targets`` (5,3,3): wanted positions of each finger's keypoints base+1..base+3; ``q_init`` (45,).
    Returns q (45,) within the joint limits.
    """
    if targets.shape != (5, 3, 3):
        raise ValueError(f"targets must have shape (5, 3, 3), got {targets.shape}")
    q = np.clip(np.asarray(q_init, dtype=np.float64), JOINT_LOWER, JOINT_UPPER).copy()
    w_sec = np.where(PRIMARY_HINGES, 0.0, IK_SECONDARY_WEIGHT).reshape(5, 9)
    # Hinge k (joint k // 3) moves the segment ends j >= k // 3.
    moves = (np.arange(3)[:, None] >= (np.arange(9)[None, :] // 3)).astype(np.float64)  # (3 points, 9 hinges)
    eye = np.eye(9)
    for _ in range(max_iterations):
        fk = finger_kinematics(geometry, q[None, :])
        pts, axes, anchors = fk.points[0], fk.axes[0], fk.anchors[0]  # (5,3,3), (5,9,3), (5,9,3)
        err = (targets - pts).reshape(5, 9)
        # d p_j / d q_k = axis_k × (p_j - anchor_k)   -> J (5, 3 points, 3 coords, 9 hinges)
        jac = cross(axes[:, None, :, :], pts[:, :, None, :] - anchors[:, None, :, :])  # (5,3,9,3)
        jac = np.swapaxes(jac * moves[None, :, :, None], 2, 3).reshape(5, 9, 9)
        qf = q.reshape(5, 9)
        jt = np.swapaxes(jac, 1, 2)
        a = jt @ jac + IK_DAMPING * eye + w_sec[:, :, None] * eye
        g = np.einsum("fij,fj->fi", jt, err) - w_sec * qf
        dq = np.linalg.solve(a, g[..., None])[..., 0].reshape(45)
        q_new = np.clip(q + dq, JOINT_LOWER, JOINT_UPPER)
        step = np.abs(q_new - q).max()
        q = q_new
        if step < IK_TOLERANCE:
            break
    return q


def _interpolate_invalid(valid: npt.NDArray[np.bool_], pos: FloatArray, q: FloatArray) -> None:
    """Fill invalid frames of positions and hinges in place: linear inside, constant beyond the ends."""
    t_all = np.arange(len(valid), dtype=np.float64)
    tv = t_all[valid]
    for arr in (pos, q):
        for c in range(arr.shape[1]):
            arr[:, c] = np.interp(t_all, tv, arr[valid, c])


def retarget_hand(seq: Sequence, hand: HandTrack, geometry: HandGeometry | None = None) -> HandReference:
    """Retarget one hand of a sequence (keypoints required) to the built-in hand; see the module docstring.

    ``geometry`` defaults to ``fit_hand_geometry`` on the sequence's own keypoints.
    """
    kp = seq.keypoints_world(hand)
    valid = np.asarray(hand.valid, dtype=bool)
    if not valid.any():
        raise SequenceValidationError.single(f"hands[{hand.side}].valid", "no frame has a valid hand")
    return retarget_keypoints(kp, valid, hand.side, geometry)


def retarget_keypoints(
    keypoints_world: FloatArray, valid: npt.NDArray[np.bool_], side: Side, geometry: HandGeometry | None = None
) -> HandReference:
    """Retarget world keypoints (T,21,3) with validity (T,) to the built-in hand of ``side``."""
    kp = np.asarray(keypoints_world, dtype=np.float64)
    t_count = kp.shape[0]
    if kp.shape != (t_count, 21, 3) or np.shape(valid) != (t_count,):
        raise ValueError(f"keypoints_world (T,21,3) and valid (T,) expected, got {kp.shape}, {np.shape(valid)}")
    geometry = geometry or fit_hand_geometry(kp, valid, side)
    vidx = np.flatnonzero(valid)
    rot_v, pos_v = kabsch(geometry.palm_points(), kp[vidx][:, list(PALM_KEYPOINTS)])
    local = np.einsum("tji,tkj->tki", rot_v, kp[vidx] - pos_v[:, None, :])  # R^T (p - t)
    finger_idx = np.array(FINGER_BASE_KEYPOINT)[:, None] + np.arange(1, 4)[None, :]
    q_v = np.zeros((len(vidx), 45))
    q_prev = np.zeros(45)
    for i in range(len(vidx)):
        iters = _FIRST_FRAME_ITERATIONS if i == 0 else IK_MAX_ITERATIONS
        q_prev = solve_fingers(geometry, local[i][finger_idx], q_prev, iters)
        q_v[i] = q_prev

    pos = np.zeros((t_count, 3))
    q = np.zeros((t_count, 45))
    pos[vidx], q[vidx] = pos_v, q_v
    _interpolate_invalid(valid, pos, q)
    rots_v = Rotation.from_matrix(rot_v)
    if len(vidx) == 1:
        rots = Rotation.from_matrix(np.repeat(rot_v, t_count, axis=0))
    else:
        rots = Slerp(vidx.astype(np.float64), rots_v)(np.clip(np.arange(t_count), vidx[0], vidx[-1]).astype(float))
    quat = rots.as_quat(scalar_first=True)
    for i in range(1, t_count):
        if np.dot(quat[i], quat[i - 1]) < 0:
            quat[i] = -quat[i]
    if quat[0, 0] < 0:
        quat = -quat

    fitted = forward_keypoints(geometry, pos, quat, q)
    residual = np.full(t_count, np.nan)
    residual[vidx] = 1e3 * np.linalg.norm(fitted[vidx] - kp[vidx], axis=2).mean(axis=1)
    targets = fitted.copy()
    targets[vidx] = kp[vidx]
    return HandReference(
        side=side,
        geometry=geometry,
        wrist_pos=pos,
        wrist_quat=quat,
        q=q,
        keypoints=targets,
        valid=valid.copy(),
        residual_mm=residual,
    )


def retarget_sequence(seq: Sequence, *, mano_dir: Path | None = None) -> list[HandReference]:
    """Retarget every hand of a sequence, in ``seq.hands`` order — the one place replay, refinement and the
    worker get their references from.

    A hand with MANO parameters, when ``mano_dir`` holds its model file, becomes a reference on its
    own MANO hand (``worker.hand.mano.pose.mano_reference``: exact hinges, per-part hulls; DESIGN §1.1-1.2);
    otherwise its keypoints are retargeted by IK. A MANO-only hand without the model file raises
    ``ManoModelMissingError`` naming the setting.
    """
    refs = []
    for hand in seq.hands:
        if hand.mano is not None:
            if mano_available([hand.side], mano_dir):
                refs.append(mano_reference(seq, hand, mano_dir))
                continue
            if hand.keypoints is None:
                mano_model_path(hand.side, mano_dir)  # raises the clear error
        refs.append(retarget_hand(seq, hand))
    return refs
