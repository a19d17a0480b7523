"""The built-in two-handed articulated example (issue #52 item 7): a hinged box opened by one hand while the
other holds it. No data and no licence needed.

A 0.8 kg base (18 x 5.6 x 9 cm) stands on the table; on its +x end sits a 0.15 kg block (5.6 x 5.6 x 9 cm), hinged
along its back bottom edge (a revolute joint about +x on the base's top face). The left hand grips the base's -x end
across its width, the right hand grips the block from above, and while the left hand holds still the right one
swings the block open by ``OPEN_RAD`` about the hinge. Both grips are the built-in example's solved box grasp
(``grasp_file``): the right hand's as it is, the left hand's its mirror image, turned a quarter about the vertical.
As in the one-hand example, the clean motion is kinematically consistent and the *observed* keypoints then get
vision-like errors (fingers hovering or sinking in, wrist offsets, jitter), and the object pose and hinge angle
small jitter.

Both parts are meshes (the block's frame sits on its hinge line, which a primitive centred on its frame could not
do), convex, so collision uses their hulls without a decomposition.
"""

from __future__ import annotations

import numpy as np

from common.articulation import ObjectJoint
from common.geometry import FloatArray, matrix_to_quat, quat_rotate
from common.sequence import HandTrack, ObjectPart, ObjectSpec, Sequence
from worker.example.box_geometry import BOX_HALF, MASS_KG
from worker.example.grasp_file import cached_box_grasp
from worker.example.sequences import FPS, Timeline, _smoothstep, observed_hinges
from worker.hand.model import (
    TEMPLATE_HAND_LENGTH,
    default_geometry,
    forward_keypoints,
)

#: Half-extents of the base (m) and its mass (kg); the block is the one-hand example's box.
BASE_HALF = np.array([0.09, BOX_HALF[1], BOX_HALF[2]])
BASE_MASS_KG = 0.8
BLOCK_MASS_KG = 0.15
#: Where the block's centre and the left hand's grip sit along the base (x, base frame).
BLOCK_X, GRIP_X = 0.05, -0.05
#: How far the right hand opens the block (rad, about the hinge).
OPEN_RAD = 1.0


#: The phases (``Timeline``): its ``lift`` is the frames over which the right hand swings the block open.
HINGED_TIMELINE = Timeline(approach=22, close=12, settle=4, lift=30, hold=8)


def box_mesh(half: FloatArray, centre: FloatArray) -> tuple[FloatArray, np.ndarray]:
    """Vertices (8, 3) and outward-wound faces (12, 3) of a box of half-extents ``half`` around ``centre``."""
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.int64)  # fmt: skip
    return signs * half + centre, faces


def hinged_box_object() -> ObjectSpec:
    """The base (frame at its centre) with the block hung from its hinge (frame on the hinge line)."""
    base_v, base_f = box_mesh(BASE_HALF, np.zeros(3))
    block_half = np.array(BOX_HALF)
    block_v, block_f = box_mesh(block_half, np.array([0.0, block_half[1], block_half[2]]))
    hinge = ObjectJoint(
        name="lid_hinge", kind="revolute", parent="base", axis=np.array([1.0, 0.0, 0.0]),
        origin_pos=np.array([BLOCK_X, -block_half[1], BASE_HALF[2]]), origin_quat=np.array([1.0, 0.0, 0.0, 0.0]),
        limits=np.array([0.0, 1.6]),
    )  # fmt: skip
    block = ObjectSpec(name="lid", mass_kg=BLOCK_MASS_KG, mesh_vertices=block_v, mesh_faces=block_f)
    return ObjectSpec(name="hinged_box", mass_kg=BASE_MASS_KG, mesh_vertices=base_v, mesh_faces=base_f,
                      parts=[ObjectPart(block, hinge)])


def _hand_motion(tl: Timeline, thumb_late: bool = True) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The right hand's grasp of a box at the origin over the timeline: wrist positions (T,3), rotations (T,4),
    hinges (T,45), in the box frame, approaching from above and closing (no opening motion)."""
    grasp = cached_box_grasp(TEMPLATE_HAND_LENGTH, BOX_HALF, MASS_KG)
    t = np.arange(tl.total, dtype=np.float64)
    approach = _smoothstep(t / max(tl.approach, 1))
    close = _smoothstep((t - tl.approach) / max(tl.close, 1))
    start_offset = np.array([-0.03, 0.0, 0.10])
    wrist_pos = grasp.wrist_pos + (1 - approach)[:, None] * start_offset
    wrist_quat = np.tile(matrix_to_quat(grasp.wrist_rot), (tl.total, 1))
    q = grasp.q_open + close[:, None] * (grasp.q - grasp.q_open)
    if thumb_late:  # the thumb closes a little after the fingers, as in the one-hand example
        thumb = _smoothstep((t - tl.approach - 0.3 * tl.close) / max(0.7 * tl.close, 1))
        q[:, :9] = grasp.q_open[:9] + thumb[:, None] * (grasp.q[:9] - grasp.q_open[:9])
    return wrist_pos, wrist_quat, q


def hinged_box_sequence(timeline: Timeline | None = None, seed: int = 0, errors: bool = True) -> Sequence:
    """Build the example (world frame = source frame, table z = 0); see the module docstring."""
    tl = timeline or HINGED_TIMELINE
    t = np.arange(tl.total, dtype=np.float64)
    close = _smoothstep((t - tl.approach) / max(tl.close, 1))
    opening = OPEN_RAD * _smoothstep((t - tl.approach - tl.close - tl.settle) / max(tl.lift, 1))
    obj = hinged_box_object()
    base_pose = np.tile(np.array([0.0, 0.0, BASE_HALF[2], 1.0, 0.0, 0.0, 0.0]), (tl.total, 1))
    parts = obj.part_poses(base_pose, opening[:, None])  # (T, 2, 7): the block's frame is its hinge line
    geometry = default_geometry("right")
    rng = np.random.default_rng(seed)
    wrist_pos, wrist_quat, q = _hand_motion(tl)

    # Right hand: the grasp of a box centred at the block's centre, carried by the block's frame.
    block_centre = np.array([0.0, BOX_HALF[1], BOX_HALF[2]])
    q_right = observed_hinges(q, close, {"index": 0.10, "middle": -0.15, "pinky": -0.2}) if errors else q
    kp = forward_keypoints(geometry, wrist_pos + (np.array([0.003, -0.002, 0.002]) if errors else 0.0), wrist_quat,
                           q_right) + block_centre  # fmt: skip
    right = quat_rotate(parts[:, 1, None, 3:], kp) + parts[:, 1, None, :3]

    # Left hand: the mirror image of the same grasp (x reflected), turned a quarter about z, at the base's -x end.
    q_left = observed_hinges(q, close, {"middle": 0.12, "ring": -0.12}) if errors else q
    kp = forward_keypoints(geometry, wrist_pos + (np.array([-0.002, 0.003, 0.0]) if errors else 0.0), wrist_quat,
                           q_left) * np.array([-1.0, 1.0, 1.0])  # fmt: skip
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    base_grip = np.array([GRIP_X, 0.0, BOX_HALF[2] - BASE_HALF[2]])  # the grasped box's centre, base frame
    left = kp @ quarter.T + base_grip + base_pose[:, None, :3]

    articulation = opening[:, None].copy()
    if errors:
        right += rng.normal(0.0, 0.0015, right.shape)
        left += rng.normal(0.0, 0.0015, left.shape)
        base_pose[:, :3] += rng.normal(0.0, 0.001, (tl.total, 3))
        base_pose[:, 3:] += rng.normal(0.0, 0.002, (tl.total, 4))
        base_pose[:, 3:] /= np.linalg.norm(base_pose[:, 3:], axis=1, keepdims=True)
        articulation = np.clip(articulation + rng.normal(0.0, 0.01, articulation.shape), 0.0, 1.6)
    valid = np.ones(tl.total, dtype=bool)
    seq = Sequence(
        name="hinged_box" if tl == HINGED_TIMELINE else f"hinged_box_{tl.total}f",
        fps=FPS,
        object=obj,
        object_pose=base_pose,
        hands=[HandTrack("right", valid, right), HandTrack("left", valid.copy(), left)],
        world_from_source=np.eye(4),
        meta={"source": "worker.example", "seed": str(seed), "errors": str(errors)},
        articulation=articulation,
    )
    return seq.validate()


def short_hinged_box_sequence(seed: int = 0, errors: bool = True) -> Sequence:
    """A 32-frame version of the hinged box, for quick tests."""
    return hinged_box_sequence(Timeline(approach=6, close=6, settle=2, lift=14, hold=4), seed, errors)
