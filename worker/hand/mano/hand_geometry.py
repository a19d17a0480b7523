"""The MANO hand as the built-in articulated hand: rest geometry, per-part convex hulls, hinge conversion.

``mano_hand_geometry`` shapes the MANO template with the subject's betas (zero pose) and describes it in
the built-in hand's terms (``worker.hand.model``): the wrist frame from the palm keypoints, finger bases,
bone lengths, and for every finger segment a *segment frame* S (x along the bone, z palmar, the built-in
convention). MANO's per-joint rotations R_k are relative to the parent and written in template coordinates;
the built-in hand composes 3 hinges per joint in its segment frames. With S_{f,-1} := S_{f,0} and
``rest_rot[f] = Wt^T S_{f,0}``, the hinge rotation of segment j is (DESIGN §1.2, "MANO input: pose parameters
-> per-joint rotations -> the 3 hinge angles")::

    H_{f,j} = S_{f,j-1}^T R_k S_{f,j} = Rz(abd) · R_{-y}(flex) · Rx(twist)

which reproduces MANO's joints and fingertips exactly (the template's rest curl is absorbed in H) and
inverts exactly (``hinges_to_rotations``). Each part's convex hull (vertices whose largest skinning weight is
that joint) is given in its MuJoCo body frame: the palm in the wrist frame, a segment in its frame S.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from common.geometry import FloatArray, IntArray
from common.sequence import Side
from worker.hand.mano.decode import MANO21_ORDER, ManoModel, load_mano_model
from worker.hand.mano.synthetic_model import MANO_FINGER_START
from worker.hand.model import (
    FINGER_BASE_KEYPOINT,
    TEMPLATE_HAND_LENGTH,
    HandGeometry,
    wrist_frames,
)

#: Thumb palmar hint in the wrist frame (right hand), the built-in template's value.
_THUMB_PALMAR = np.array([0.0, 0.70, 0.70])


@dataclass(frozen=True)
class PartHull:
    """Convex hull of one MANO part in its body frame: ``vertices`` (n,3) metres, ``faces`` (m,3)."""

    name: str  # "palm" or "<finger><segment 1-3>", e.g. "index2"
    mano_joint: int
    vertices: FloatArray
    faces: IntArray


@dataclass(frozen=True)
class ManoHandGeometry:
    """A subject's MANO hand in the built-in hand's terms (template coordinates unless noted).

    ``geometry``: a ``HandGeometry`` for the MJCF generator / FK (capsule radii fitted to the part vertices);
    ``hulls``: 16 parts (palm + 15 segments, thumb..pinky, segments 1..3), body-frame vertices;
    ``wrist_frame`` Wt (3,3) and ``wrist_origin`` (3,) = rest J0; ``segment_frames`` S (5,3,3,3);
    ``joints`` (16,3) rest joints (MANO order); ``keypoints`` (21,3) rest keypoints (MANO21 order).
    """

    side: Side
    geometry: HandGeometry
    hulls: list[PartHull]
    wrist_frame: FloatArray
    wrist_origin: FloatArray
    segment_frames: FloatArray
    joints: FloatArray
    keypoints: FloatArray


FINGER_NAMES = ("thumb", "index", "middle", "ring", "pinky")


def shaped_rest(model: ManoModel, betas: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Rest (zero-pose) vertices (V,3) and joints (16,3) for ``betas`` — what smplx computes at zero pose."""
    shapedirs = np.asarray(model.data["shapedirs"], dtype=np.float64)
    b = np.zeros(shapedirs.shape[-1])
    betas = np.asarray(betas, dtype=np.float64).reshape(-1)[: b.size]
    b[: betas.size] = betas
    verts = np.asarray(model.data["v_template"], dtype=np.float64) + shapedirs @ b
    reg = model.data["J_regressor"]
    joints = np.asarray(reg @ verts, dtype=np.float64)
    return verts, joints


def _segment_frames(kp: FloatArray, wrist: FloatArray, side: Side) -> FloatArray:
    frames = np.zeros((5, 3, 3, 3))
    thumb_hint = wrist @ (_THUMB_PALMAR * ([1, -1, 1] if side == "left" else 1))
    for f, base in enumerate(FINGER_BASE_KEYPOINT):
        hint = thumb_hint if f == 0 else wrist[:, 2]
        for j in range(3):
            x = kp[base + j + 1] - kp[base + j]
            x /= np.linalg.norm(x)
            z = hint - np.dot(hint, x) * x
            z /= np.linalg.norm(z)
            frames[f, j] = np.column_stack([x, np.cross(z, x), z])
    return frames


def _hull(points: FloatArray) -> tuple[FloatArray, IntArray]:
    hull = ConvexHull(points)
    keep = hull.vertices
    remap = -np.ones(len(points), dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    return points[keep], remap[hull.simplices]


def mano_hand_geometry(mano_dir: Path | str | None, side: Side, betas: FloatArray) -> ManoHandGeometry:
    """The subject's MANO hand (``betas``) as built-in hand geometry plus per-part convex hulls."""
    model = load_mano_model(side, mano_dir)
    verts, joints = shaped_rest(model, betas)
    kp = np.concatenate([joints, verts[list(model.tip_vertex_ids)]])[list(MANO21_ORDER)]
    wrist = wrist_frames(kp[None], side)[0]
    frames = _segment_frames(kp, wrist, side)
    bases = np.array([wrist.T @ (kp[b] - kp[0]) for b in FINGER_BASE_KEYPOINT])
    lengths = np.array([[np.linalg.norm(kp[b + j + 1] - kp[b + j]) for j in range(3)] for b in FINGER_BASE_KEYPOINT])

    part = np.asarray(model.data["weights"]).argmax(axis=1)
    hulls = [PartHull("palm", 0, *_hull((verts[part == 0] - kp[0]) @ wrist))]
    radii = np.zeros((5, 3))
    for f, start in enumerate(MANO_FINGER_START):
        for j in range(3):
            k = start + j
            local = (verts[part == k] - joints[k]) @ frames[f, j]  # S^T (v - J_k)
            radii[f, j] = float(np.median(np.linalg.norm(local[:, 1:], axis=1)))
            hulls.append(PartHull(f"{FINGER_NAMES[f]}{j + 1}", k, *_hull(local)))
    palm_z = hulls[0].vertices[:, 2]
    hand_length = float(np.linalg.norm(bases[2]) + lengths[2].sum())
    geometry = HandGeometry(
        side=side,
        bases=bases,
        rest_rot=np.einsum("ji,fjk->fik", wrist, frames[:, 0]),  # Wt^T S_f0
        lengths=lengths,
        radii=radii,
        palm_half_thickness=float(np.percentile(palm_z, 95) - np.percentile(palm_z, 5)) / 2,
        scale=hand_length / TEMPLATE_HAND_LENGTH,
        meta={"mano_vertices": float(len(verts))},
        part_meshes={h.name: h.vertices for h in hulls},  # mesh geoms in the MJCF (DESIGN §1.1)
    )
    return ManoHandGeometry(side, geometry, hulls, wrist, kp[0].copy(), frames, joints, kp)


# ---------------------------------------------------------------------- rotations <-> hinges


def rotations_to_hinges(rotations: FloatArray, mgeo: ManoHandGeometry) -> FloatArray:
    """(T,16,3,3) MANO local rotations -> (T,45) hinge angles in ``HINGE_NAMES`` order (see module doc)."""
    rot = np.asarray(rotations, dtype=np.float64)
    if rot.ndim != 4 or rot.shape[1:] != (16, 3, 3):
        raise ValueError(f"rotations must have shape (T, 16, 3, 3), got {rot.shape}")
    q = np.zeros((rot.shape[0], 5, 3, 3))
    for f, start in enumerate(MANO_FINGER_START):
        for j in range(3):
            s_prev, s_cur = mgeo.segment_frames[f, max(j - 1, 0)], mgeo.segment_frames[f, j]
            h = s_prev.T @ rot[:, start + j] @ s_cur
            zyx = Rotation.from_matrix(h).as_euler("ZYX")  # intrinsic: Rz(a) Ry(b) Rx(c)
            q[:, f, j] = np.column_stack([zyx[:, 0], -zyx[:, 1], zyx[:, 2]])  # flexion is about -y
    return q.reshape(-1, 45)


def hinges_to_rotations(q: FloatArray, mgeo: ManoHandGeometry) -> FloatArray:
    """(T,45) hinge angles -> (T,15,3,3) MANO local finger rotations (joints 1..15), the exact inverse."""
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 45:
        raise ValueError(f"q must have shape (T, 45), got {q.shape}")
    qf = q.reshape(-1, 5, 3, 3)
    out = np.zeros((q.shape[0], 15, 3, 3))
    for f, start in enumerate(MANO_FINGER_START):
        for j in range(3):
            s_prev, s_cur = mgeo.segment_frames[f, max(j - 1, 0)], mgeo.segment_frames[f, j]
            angles = np.column_stack([qf[:, f, j, 0], -qf[:, f, j, 1], qf[:, f, j, 2]])
            h = Rotation.from_euler("ZYX", angles).as_matrix()
            out[:, start + j - 1] = s_prev @ h @ s_cur.T
    return out
