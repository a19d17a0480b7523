"""Mirror a sequence through a vertical world plane: a right-hand demonstration becomes its exact left-hand
mirror image and back (issue #15 item 5: "a mirrored sequence must refine as well as its original").

The reflection is ``M = I - 2 n n^T`` through the world plane with unit normal ``n`` (horizontal, so the table
and gravity are unchanged) through the world origin. Everything is expressed in the world frame of the result
(``world_from_source`` = identity):

* hand keypoints ``p -> M p``, each hand's side swapped (a reflection turns a right hand into a left one); MANO
  parameters are dropped (a reflected MANO pose is not a MANO pose of the other hand's model without a
  re-fit), so the mirrored hands are keypoint-driven;
* the object is reflected in its own frame by ``S = diag(-1, 1, 1)`` (mesh vertices ``v -> S v``, faces
  re-wound so normals still point out) and its pose becomes ``R -> M R S``, ``t -> M t`` — a proper rotation,
  and the world surface ``R' v' + t' = M (R v + t)`` is the reflected one. A box, cylinder, capsule or sphere is
  symmetric under ``S``, so a primitive stays the same primitive;
* an articulated object (``common.articulation``): every part is reflected in its own frame by ``S`` in the same
  way, so each part's pose must become ``M R_k S``, ``M t_k``. Forward kinematics gives exactly that when every
  joint's parent-to-child transform ``T`` becomes ``S T S``: the origin ``p -> S p``, its rotation ``R -> S R S``,
  a prismatic axis ``a -> S a`` (a direction) and a revolute axis ``a -> -S a`` (a pseudo-vector: ``S Rot(a, q) S =
  Rot(det(S) S a, q)``); the joint values and limits stay as they are.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from common.articulation import ObjectJoint
from common.sequence import FloatArray, HandTrack, ObjectPart, ObjectSpec, Sequence, Side

#: Reflection of the object frame (its x axis): the object's own mirror image.
_OBJECT_REFLECTION = np.diag([-1.0, 1.0, 1.0])
OTHER_SIDE: dict[Side, Side] = {"right": "left", "left": "right"}


def reflection(normal: FloatArray | tuple[float, float, float] = (1.0, 0.0, 0.0)) -> FloatArray:
    """3x3 reflection through the plane through the origin with the given normal (must be horizontal)."""
    n = np.asarray(normal, dtype=np.float64)
    if n.shape != (3,) or not np.isfinite(n).all() or np.linalg.norm(n) < 1e-9:
        raise ValueError(f"normal must be a finite non-zero 3-vector, got {normal!r}")
    n = n / np.linalg.norm(n)
    if abs(n[2]) > 1e-9:
        raise ValueError("the mirror plane must be vertical (normal with z = 0): the table and gravity stay put")
    return np.eye(3) - 2.0 * np.outer(n, n)


def _quat_to_matrix(q: FloatArray) -> FloatArray:
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.from_quat(q, scalar_first=True).as_matrix())


def _matrix_to_quat(r: FloatArray) -> FloatArray:
    from scipy.spatial.transform import Rotation

    q = np.asarray(Rotation.from_matrix(r).as_quat(scalar_first=True))
    for i in range(1, len(q)):  # sign-continuous, as the loaders keep it
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
    return q if q[0, 0] >= 0 else -q


def mirror_object(obj: ObjectSpec) -> ObjectSpec:
    """The object's mirror image in its own frame (``S`` of the module docstring), every part of an articulated
    object in its own frame and every joint with it."""
    parts = [ObjectPart(mirror_object(p.shape), mirror_joint(p.joint)) for p in obj.parts]
    if obj.mesh_vertices is None:
        return replace(obj, size=None if obj.size is None else obj.size.copy(), parts=parts)
    faces = None if obj.mesh_faces is None else obj.mesh_faces[:, ::-1].copy()
    return replace(obj, mesh_vertices=obj.mesh_vertices @ _OBJECT_REFLECTION.T, mesh_faces=faces, parts=parts)


def mirror_joint(joint: ObjectJoint) -> ObjectJoint:
    """The joint between two mirrored parts: its transform ``T`` conjugated, ``S T S`` (module docstring)."""
    s = _OBJECT_REFLECTION
    origin_rot = s @ _quat_to_matrix(np.asarray(joint.origin_quat, dtype=np.float64)[None])[0] @ s
    axis = s @ np.asarray(joint.axis, dtype=np.float64)
    return replace(
        joint, axis=-axis if joint.kind == "revolute" else axis,
        origin_pos=s @ np.asarray(joint.origin_pos, dtype=np.float64), origin_quat=_matrix_to_quat(origin_rot[None])[0],
        limits=np.asarray(joint.limits, dtype=np.float64).copy(),
    )  # fmt: skip


def mirror_sequence(seq: Sequence, normal: FloatArray | tuple[float, float, float] = (1.0, 0.0, 0.0)) -> Sequence:
    """The mirror image of ``seq`` through the vertical world plane with ``normal`` (default: the world yz
    plane); see the module docstring. Mirroring twice gives the original back (in world coordinates)."""
    m = reflection(normal)
    pose = seq.object_pose_world()
    rot = m @ _quat_to_matrix(pose[:, 3:]) @ _OBJECT_REFLECTION
    object_pose = np.concatenate([pose[:, :3] @ m.T, _matrix_to_quat(rot)], axis=1)
    hands = []
    for hand in seq.hands:
        if hand.keypoints is None:
            raise ValueError(f"the {hand.side} hand has no keypoints: decode MANO parameters before mirroring")
        hands.append(HandTrack(side=OTHER_SIDE[hand.side], valid=hand.valid.copy(),
                               keypoints=seq.keypoints_world(hand) @ m.T))
    return Sequence(
        name=f"{seq.name}__mirrored",
        fps=seq.fps,
        object=mirror_object(seq.object),
        object_pose=object_pose,
        hands=hands,
        frame_start=seq.frame_start,
        world_from_source=np.eye(4),
        articulation=None if seq.articulation is None else seq.articulation.copy(),
        meta={**seq.meta, "mirrored": "through the world plane with normal " + " ".join(f"{v:g}" for v in
                                                                                         np.ravel(normal))},
    ).validate()
