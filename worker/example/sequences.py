"""The built-in synthetic grasp-and-lift (issue item 9): no data and no licence needed.

A right hand (the built-in template hand) comes down over a 0.2 kg box (5.6 x 5.6 x 9 cm) standing on the
table, closes the index, middle and ring fingers on one face and the thumb on the opposite face (a grasp solved
once by ``grasp_file`` and shipped in ``worker/example/data/example_grasp.npz``; each finger stops 4 mm
inside the surface so the position servos press), lifts the box 20 cm and holds it. The clean trajectory is
kinematically consistent: the object rests until the hand has closed, then moves rigidly with the wrist. The
*observed* keypoints then get vision-like errors — a hovering middle finger and pinky, index and ring fingers
that sink into the box, a wrist offset and per-keypoint jitter — and the object pose gets small jitter, so the
example looks like a vision-aligned demonstration.

``example_sequence()`` is the 72-frame (2.4 s at 30 fps) demo; ``short_example_sequence()`` a 24-frame version
for quick tests. Both are deterministic (seeded).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import FloatArray, matrix_to_quat
from common.sequence import HandTrack, ObjectSpec, Sequence
from worker.example.box_geometry import BOX_HALF, MASS_KG
from worker.example.grasp_file import cached_box_grasp
from worker.hand.model import (
    FINGERS,
    JOINT_LOWER,
    JOINT_UPPER,
    TEMPLATE_HAND_LENGTH,
    default_geometry,
    forward_keypoints,
)

FPS = 30.0


@dataclass(frozen=True)
class Timeline:
    """Frame counts of the phases: approach, close, settle, lift (the motion the grasp makes: the hinged box's
    opening), hold."""

    approach: int = 22
    close: int = 12
    settle: int = 4
    lift: int = 26
    hold: int = 8

    @property
    def total(self) -> int:
        return self.approach + self.close + self.settle + self.lift + self.hold


def _smoothstep(x: FloatArray) -> FloatArray:
    x = np.clip(x, 0.0, 1.0)
    return np.asarray(x * x * (3 - 2 * x))


#: Finger flexion direction (MCP, PIP, DIP) used for the observation errors.
_FLEX_PATTERN = np.array([0.0, 0.9, 0.0, 0.0, 1.0, 0.0, 0.0, 0.7, 0.0])


def observed_hinges(q: FloatArray, close: FloatArray, errors: dict[str, float]) -> FloatArray:
    """Hinge angles (T, 45) with per-finger flexion errors (radians along ``_FLEX_PATTERN``, + sinks into the
    object, - hovers) growing with the grasp's closing (``close``, 0..1 per frame), within the joint limits."""
    out = q.copy()
    for name, delta in errors.items():
        f = FINGERS.index(name)
        out[:, 9 * f : 9 * f + 9] += close[:, None] * delta * _FLEX_PATTERN
    return np.asarray(np.clip(out, JOINT_LOWER, JOINT_UPPER))


def _object_spec(half_extents: FloatArray) -> ObjectSpec:
    return ObjectSpec(name="synthetic_box", mass_kg=MASS_KG, primitive="box", size=np.asarray(half_extents))


def synthetic_grasp_and_lift(timeline: Timeline | None = None, seed: int = 0, errors: bool = True) -> Sequence:
    """Build the example sequence (world frame = source frame, table z = 0); see the module docstring."""
    tl = timeline or Timeline()
    geometry = default_geometry("right")
    grasp = cached_box_grasp(TEMPLATE_HAND_LENGTH, BOX_HALF, MASS_KG)
    half = np.array(BOX_HALF)
    q_grasp = grasp.q
    pos_g = grasp.wrist_pos + np.array([0.0, 0.0, half[2]])
    quat_g = matrix_to_quat(grasp.wrist_rot)
    t = np.arange(tl.total, dtype=np.float64)
    approach = _smoothstep(t / max(tl.approach, 1))
    t_close0 = tl.approach
    close = _smoothstep((t - t_close0) / max(tl.close, 1))
    t_lift0 = tl.approach + tl.close + tl.settle
    lift = 0.20 * _smoothstep((t - t_lift0) / max(tl.lift, 1))

    start_offset = np.array([-0.03, 0.0, 0.10])  # the hand comes down from above
    wrist_pos = pos_g + (1 - approach)[:, None] * start_offset + lift[:, None] * np.array([0.0, 0.0, 1.0])
    wrist_quat = np.tile(quat_g, (tl.total, 1))
    q_open = grasp.q_open
    q = q_open + close[:, None] * (q_grasp - q_open)
    # The thumb closes a little after the fingers, so it presses the box against fingers already in place.
    thumb_close = _smoothstep((t - t_close0 - 0.3 * tl.close) / max(0.7 * tl.close, 1))
    q[:, :9] = q_open[:9] + thumb_close[:, None] * (q_grasp[:9] - q_open[:9])
    obj_pose = np.tile(np.array([0.0, 0.0, half[2], 1.0, 0.0, 0.0, 0.0]), (tl.total, 1))
    obj_pose[:, 2] += lift  # rigidly with the wrist once lifting starts (lift is 0 before)

    rng = np.random.default_rng(seed)
    if errors:
        q_seen = observed_hinges(q, close, {"index": 0.12, "middle": -0.15, "ring": 0.10, "pinky": -0.2})
        wrist_seen = wrist_pos + np.array([0.003, -0.002, 0.002])
        keypoints = forward_keypoints(geometry, wrist_seen, wrist_quat, q_seen)
        keypoints += rng.normal(0.0, 0.0015, keypoints.shape)
        obj_pose[:, :3] += rng.normal(0.0, 0.001, (tl.total, 3))
        obj_pose[:, 3:] += rng.normal(0.0, 0.002, (tl.total, 4))
        obj_pose[:, 3:] /= np.linalg.norm(obj_pose[:, 3:], axis=1, keepdims=True)
    else:
        keypoints = forward_keypoints(geometry, wrist_pos, wrist_quat, q)
    hand = HandTrack(side="right", valid=np.ones(tl.total, dtype=bool), keypoints=keypoints)
    seq = Sequence(
        name="synthetic_grasp_and_lift" if tl == Timeline() else f"synthetic_grasp_and_lift_{tl.total}f",
        fps=FPS,
        object=_object_spec(half),
        object_pose=obj_pose,
        hands=[hand],
        world_from_source=np.eye(4),
        meta={"source": "worker.example", "seed": str(seed), "errors": str(errors)},
    )
    return seq.validate()


def example_sequence(seed: int = 0, errors: bool = True) -> Sequence:
    """The 72-frame demo sequence (2.4 s at 30 fps)."""
    return synthetic_grasp_and_lift(Timeline(), seed=seed, errors=errors)


def short_example_sequence(seed: int = 0, errors: bool = True) -> Sequence:
    """A 24-frame version (0.8 s) of the same grasp-and-lift, for quick tests."""
    return synthetic_grasp_and_lift(Timeline(approach=5, close=5, settle=2, lift=9, hold=3), seed=seed, errors=errors)
