"""A small grasp synthesiser for the built-in example: the built-in hand grasping an upright box from above.

Least squares over the wrist pose (rotation vector, position; box frame) and the 45 hinges within their limits:
the thumb tip sinks ``penetration`` into the -x face and the index, middle and ring tips into the +x face
(opposition), every other capsule stays outside the box, the palm faces down, and the hinges stay near a
natural half-closed hand. Deterministic (fixed start, no randomness).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from common.geometry import FloatArray
from worker.example.box_geometry import BoxGrasp, box_sdf, capsule_samples
from worker.hand.model import JOINT_LOWER, JOINT_UPPER, HandGeometry

#: Natural half-closed hand (the regulariser's target and the solver's start).
_NATURAL = np.zeros(45)
_NATURAL[:9] = [0.5, 0.4, 0.0, 0.0, 0.5, 0.0, 0.0, 0.5, 0.0]
for _f in range(1, 5):
    _NATURAL[9 * _f : 9 * _f + 9] = [0.0, 0.6, 0.0, 0.0, 0.9, 0.0, 0.0, 0.5, 0.0]
_PAD_FINGERS = (1, 2, 3)  # index, middle, ring on the +x face; thumb (0) on the -x face


def _palm_samples(geometry: HandGeometry) -> FloatArray:
    xs = np.linspace(0.02, float(geometry.bases[1:, 0].mean()), 4)
    ys = np.linspace(float(geometry.bases[1:, 1].min()), float(geometry.bases[1:, 1].max()), 4)
    return np.array([[x, y, 0.0] for x in xs for y in ys])


def synthesize_box_grasp(geometry: HandGeometry, half: FloatArray, penetration: float = 0.002) -> BoxGrasp:
    """Solve the grasp of the module docstring for a box of half-extents ``half`` (3,)."""
    half = np.asarray(half, dtype=np.float64)
    palm_pts = _palm_samples(geometry)
    pads = [0, *_PAD_FINGERS]
    keep = np.ones((5, 3, 7), dtype=bool)
    keep[pads, 2] = False  # distal segments of the pad fingers are handled by the contact residual
    down = np.array([0.0, 0.0, -1.0])
    face_sign = np.array([-1.0, 1.0, 1.0, 1.0])

    def batch(x: FloatArray) -> FloatArray:
        rot = Rotation.from_rotvec(x[:, :3]).as_matrix()  # (B,3,3)
        pos, q = x[:, 3:6], x[:, 6:]
        pts, radii, tips = capsule_samples(geometry, q)
        world = np.einsum("bij,bfskj->bfski", rot, pts) + pos[:, None, None, None, :]
        tips_w = np.einsum("bij,bfj->bfi", rot, tips) + pos[:, None, :]
        clearance = box_sdf(world, half) - radii  # (B,5,3,7)
        contact = 10.0 * (clearance[:, pads, 2].min(axis=2) + penetration)  # distal capsules just sink in
        side = 3.0 * np.minimum(face_sign * tips_w[:, pads, 0] - (half[0] - 0.01), 0.0)  # on the right face
        face = 10.0 * np.maximum(np.abs(tips_w[:, pads, 1:]) - (half[1:] - 0.01), 0.0).reshape(len(x), -1)
        pen = 10.0 * np.maximum(-clearance[:, keep], 0.0)
        palm_w = np.einsum("bij,pj->bpi", rot, palm_pts) + pos[:, None, :]
        palm = 10.0 * np.maximum(geometry.palm_half_thickness - box_sdf(palm_w, half), 0.0)
        up = 0.02 * (rot[:, :, 2] - down)
        reg = 0.003 * (q - _NATURAL)
        return np.concatenate([contact, side, face, pen, palm, up, reg], axis=1)

    def jac(x: FloatArray) -> FloatArray:
        eps = 1e-6
        xs = np.vstack([x, x + eps * np.eye(len(x))])
        r = batch(xs)
        return np.asarray((r[1:] - r[0]).T / eps)

    # Start: palm down above the box, fingers along +x (wrist frame: x fingers, z palmar, y = z × x).
    rot0 = np.column_stack([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    x0 = np.concatenate([Rotation.from_matrix(rot0).as_rotvec(), [-0.06, 0.0, half[2] + 0.04], _NATURAL])
    lo = np.concatenate([np.full(6, -np.inf), JOINT_LOWER])
    hi = np.concatenate([np.full(6, np.inf), JOINT_UPPER])
    sol = least_squares(
        lambda x: batch(x[None, :])[0], np.clip(x0, lo + 1e-9, hi - 1e-9), jac=jac, bounds=(lo, hi), max_nfev=400
    )
    q = sol.x[6:]
    # Open hand for the approach: a quarter of the grasp's hinge angles.
    q_open = np.clip(0.25 * q, JOINT_LOWER, JOINT_UPPER)
    return BoxGrasp(
        wrist_rot=Rotation.from_rotvec(sol.x[:3]).as_matrix(),
        wrist_pos=sol.x[3:6].copy(),
        q=q,
        q_open=q_open,
        cost=float(np.linalg.norm(sol.fun)),
    )


def close_to_contact(
    geometry: HandGeometry, grasp: BoxGrasp, half: FloatArray, penetration: float = 0.002
) -> FloatArray:
    """Per finger, the point on the straight path ``q_open -> q`` where its capsules first sink ``penetration``
    into the box (fingers that never touch keep ``q``): the least-squares grasp may overshoot by millimetres,
    and a finger that sinks deep pushes the box before the others arrive."""
    alphas = np.linspace(0.0, 1.0, 201)
    q_out = grasp.q.copy()
    for f in range(5):
        sl = slice(9 * f, 9 * f + 9)
        trials = np.tile(grasp.q, (len(alphas), 1))
        trials[:, sl] = grasp.q_open[sl] + alphas[:, None] * (grasp.q[sl] - grasp.q_open[sl])
        pts, radii, _ = capsule_samples(geometry, trials)
        world = pts[:, f] @ grasp.wrist_rot.T + grasp.wrist_pos
        clearance = (box_sdf(world, np.asarray(half)) - radii[:, f]).min(axis=(1, 2))
        hit = np.flatnonzero(clearance <= -penetration)
        if hit.size:
            q_out[sl] = trials[hit[0], sl]
    return q_out
