"""The built-in articulated hand (DESIGN §1.1): geometry, hinge names, joint limits and NumPy kinematics.

Topology is MANO's: a palm (the wrist frame) and 5 fingers of 3 segments each; every finger joint is 3 hinges
(45 DoF). Frames, used everywhere (IK, MJCF, losses):

* **Wrist frame** (the palm body): origin at keypoint 0; x towards the middle MCP (keypoint 9); z the palmar
  normal of the (wrist, index MCP, pinky MCP) plane; y = z × x. The definition is the same for both sides, so
  a left hand is the mirror image of a right hand through the wrist frame's xz plane.
* **Finger rest frame** (per finger, fixed in the wrist frame): x along the straight finger, z palmar. Segment
  bodies are chained along local x: segment j starts at keypoint ``base + j`` and ends at the next keypoint.
* **Hinges** of a joint, in kinematic order (MuJoCo composes a body's joints left to right, R = R0·R1·R2):
  abduction about local z, flexion about local −y (positive bends towards the palm), twist about local x.

``forward_keypoints`` is the reference kinematics; the MJCF in ``hand_mjcf`` reproduces it exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from common.errors import SequenceValidationError
from common.geometry import FloatArray, quat_to_matrix
from common.sequence import Side

FINGERS: tuple[str, ...] = ("thumb", "index", "middle", "ring", "pinky")
HINGE_AXES: tuple[str, ...] = ("abd", "flex", "twist")
#: The 45 hinges, finger-major (thumb, index, middle, ring, pinky), joints 1..3, axes (abd, flex, twist).
HINGE_NAMES: tuple[str, ...] = tuple(f"{f}{j}_{a}" for f in FINGERS for j in (1, 2, 3) for a in HINGE_AXES)
#: The hand's bodies without the side prefix: the palm, then the 15 segments finger-major ("thumb1".."pinky3").
BODY_PARTS: tuple[str, ...] = ("palm", *(f"{f}{j}" for f in FINGERS for j in (1, 2, 3)))
#: Keypoint index of each finger's first joint (MANO21 order); the finger's keypoints are base..base+3.
FINGER_BASE_KEYPOINT: tuple[int, ...] = (1, 5, 9, 13, 17)
#: Palm keypoints (rigid in the wrist frame): wrist and the 5 finger bases.
PALM_KEYPOINTS: tuple[int, ...] = (0, 1, 5, 9, 13, 17)
#: Per hinge (HINGE_NAMES order), the sign that maps a hand's hinge angles to its mirror image's: a reflection
#: through the wrist frame's xz plane keeps every flexion and negates every abduction and twist (rotations about
#: local z and x reverse, rotations about local y do not), so the left hand that mirrors a right hand at ``q`` is
#: at ``MIRROR_SIGNS * q``. Joint limits of abduction and twist are symmetric, so the map stays within them.
MIRROR_SIGNS: FloatArray = np.array([-1.0 if a in ("abd", "twist") else 1.0 for _f in FINGERS for _j in (1, 2, 3)
                                     for a in HINGE_AXES])
#: Hinge axes in the segment frame, in HINGE_AXES order.
AXIS_VECTORS: FloatArray = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
#: Hand length (wrist to middle fingertip) of the template hand, metres; widths scale with it.
TEMPLATE_HAND_LENGTH = 0.18

# Anatomical limits (rad) per (joint, axis) for the four fingers and for the thumb. The flexion ranges follow
# hand-anatomy tables (MCP ~ -20..90 deg, PIP ~ 0..110, DIP ~ -10..85); abduction/twist are small except at the
# MCP and at the thumb's CMC, which must reach opposition.
_FINGER_LIMITS = np.array(
    [
        [[-0.40, 0.40], [-0.45, 1.65], [-0.35, 0.35]],  # MCP: abd, flex, twist
        [[-0.20, 0.20], [-0.15, 1.95], [-0.25, 0.25]],  # PIP
        [[-0.20, 0.20], [-0.30, 1.60], [-0.25, 0.25]],  # DIP
    ]
)
_THUMB_LIMITS = np.array(
    [
        [[-0.90, 0.90], [-0.80, 1.30], [-0.90, 0.90]],  # CMC
        [[-0.40, 0.40], [-0.50, 1.20], [-0.40, 0.40]],  # MCP
        [[-0.25, 0.25], [-0.50, 1.50], [-0.30, 0.30]],  # IP
    ]
)
#: (45, 2) lower/upper limits in HINGE_NAMES order.
JOINT_LIMITS: FloatArray = np.concatenate([_THUMB_LIMITS.reshape(9, 2)] + [_FINGER_LIMITS.reshape(9, 2)] * 4)
JOINT_LOWER: FloatArray = JOINT_LIMITS[:, 0].copy()
JOINT_UPPER: FloatArray = JOINT_LIMITS[:, 1].copy()
#: True for the hinges keypoints determine well (all flexions, the first joint's abduction); the others
#: (twists, distal abductions) are regularised towards the previous frame by the IK.
PRIMARY_HINGES: npt.NDArray[np.bool_] = np.array(
    [(a == "flex") or (a == "abd" and j == 1) for _f in FINGERS for j in (1, 2, 3) for a in HINGE_AXES]
)

# Template right hand in the wrist frame (metres): finger-base positions, segment lengths, capsule radii.
_TEMPLATE_BASES = np.array(
    [[0.030, -0.024, 0.008], [0.090, -0.024, 0.0], [0.093, 0.0, 0.0], [0.086, 0.019, 0.002], [0.077, 0.036, 0.0]]
)
_TEMPLATE_LENGTHS = np.array(
    [[0.040, 0.032, 0.028], [0.042, 0.025, 0.022], [0.046, 0.028, 0.024], [0.043, 0.027, 0.023], [0.034, 0.020, 0.021]]
)
_TEMPLATE_RADII = np.array(
    [[0.0115, 0.0100, 0.0090], [0.0095, 0.0085, 0.0075], [0.0095, 0.0085, 0.0075], [0.0090, 0.0080, 0.0072],
     [0.0080, 0.0072, 0.0065]]
)  # fmt: skip
_TEMPLATE_THUMB_DIR = np.array([0.70, -0.60, 0.38])
_TEMPLATE_THUMB_PALMAR = np.array([0.0, 0.70, 0.70])
PALM_HALF_THICKNESS = 0.012  # template value; scaled with hand length


@dataclass(frozen=True)
class HandGeometry:
    """Per-side size and layout of the built-in hand (all in the wrist frame, metres).

    ``bases`` (5,3): first-joint position of each finger; ``rest_rot`` (5,3,3): finger rest frame (columns x, y,
    z in the wrist frame); ``lengths`` (5,3): segment lengths; ``radii`` (5,3): capsule radii;
    ``palm_half_thickness``; ``scale``: hand length / template hand length. ``part_meshes`` (optional, the MANO
    hand, DESIGN §1.1): body name without side ("palm", "index2", ...) -> convex-hull vertices (n,3) in that
    body's frame; ``hand_mjcf`` then emits mesh geoms for those bodies instead of the box/capsules.
    """

    side: Side
    bases: FloatArray
    rest_rot: FloatArray
    lengths: FloatArray
    radii: FloatArray
    palm_half_thickness: float
    scale: float
    meta: dict[str, float] = field(default_factory=dict)
    part_meshes: dict[str, FloatArray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, shape in (("bases", (5, 3)), ("rest_rot", (5, 3, 3)), ("lengths", (5, 3)), ("radii", (5, 3))):
            arr = getattr(self, name)
            if np.shape(arr) != shape:
                raise ValueError(f"HandGeometry.{name} must have shape {shape}, got {np.shape(arr)}")
        for part, verts in self.part_meshes.items():
            if part not in BODY_PARTS:
                raise ValueError(f"HandGeometry.part_meshes: unknown body {part!r} (expected one of {BODY_PARTS})")
            if np.ndim(verts) != 2 or np.shape(verts)[1] != 3 or len(verts) < 4:
                raise ValueError(f"HandGeometry.part_meshes[{part!r}] must have shape (n>=4, 3), got {np.shape(verts)}")
        if self.side not in ("right", "left"):
            raise ValueError(f"HandGeometry.side must be 'right' or 'left', got {self.side!r}")

    @property
    def hand_length(self) -> float:
        """Wrist to middle fingertip with straight fingers (metres)."""
        return float(np.linalg.norm(self.bases[2]) + self.lengths[2].sum())

    def palm_points(self) -> FloatArray:
        """(6,3) palm keypoints (PALM_KEYPOINTS order) in the wrist frame."""
        return np.vstack([np.zeros(3), self.bases])

    def distal_capsule_ends(self) -> FloatArray:
        """(5,) how far each distal capsule's axis runs from its DIP joint: a radius short of the fingertip
        keypoint, so the capsule *ends* at the keypoint (MANO tips lie on the skin surface), and never under 0.3
        of the segment (a short, thick fingertip)."""
        lengths, radii = self.lengths[:, 2], self.radii[:, 2]
        return np.asarray(np.maximum(lengths - radii, 0.3 * lengths), dtype=np.float64)


def _mirror(side: Side) -> FloatArray:
    """Left hands are right hands mirrored through the wrist frame's xz plane (y -> -y)."""
    return np.array([1.0, -1.0, 1.0]) if side == "left" else np.ones(3)


def _rest_frames(bases: FloatArray, thumb_dir: FloatArray, thumb_palmar: FloatArray) -> FloatArray:
    """Rest frames: fingers point along their metacarpal (wrist -> base, in the palm plane), z palmar."""
    rots = np.empty((5, 3, 3))
    for f in range(5):
        if f == 0:
            x, z_hint = thumb_dir, thumb_palmar
        else:
            x, z_hint = np.array([bases[f, 0], bases[f, 1], 0.0]), np.array([0.0, 0.0, 1.0])
        x = x / np.linalg.norm(x)
        z = z_hint - np.dot(z_hint, x) * x
        z /= np.linalg.norm(z)
        rots[f] = np.column_stack([x, np.cross(z, x), z])
    return rots


def default_geometry(side: Side = "right", hand_length: float = TEMPLATE_HAND_LENGTH) -> HandGeometry:
    """The template hand of the given side, uniformly scaled to ``hand_length`` (metres)."""
    s = hand_length / TEMPLATE_HAND_LENGTH
    m = _mirror(side)
    bases = _TEMPLATE_BASES * s * m
    return HandGeometry(
        side=side,
        bases=bases,
        rest_rot=_rest_frames(bases, _TEMPLATE_THUMB_DIR * m, _TEMPLATE_THUMB_PALMAR * m),
        lengths=_TEMPLATE_LENGTHS * s,
        radii=_TEMPLATE_RADII * s,
        palm_half_thickness=PALM_HALF_THICKNESS * s,
        scale=s,
    )


# ---------------------------------------------------------------------- frames from keypoints


def wrist_frames(keypoints: FloatArray, side: Side) -> FloatArray:
    """(T,3,3) wrist-frame rotations (columns x, y, z in world) built from keypoints (T,21,3)."""
    kp = np.asarray(keypoints, dtype=np.float64)
    if kp.ndim != 3 or kp.shape[1:] != (21, 3):
        raise ValueError(f"keypoints must have shape (T, 21, 3), got {kp.shape}")
    x = kp[:, 9] - kp[:, 0]
    x /= np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
    a, b = kp[:, 5] - kp[:, 0], kp[:, 17] - kp[:, 0]
    z = np.cross(a, b) if side == "right" else np.cross(b, a)
    z -= np.sum(z * x, axis=1, keepdims=True) * x
    z /= np.maximum(np.linalg.norm(z, axis=1, keepdims=True), 1e-12)
    return np.stack([x, np.cross(z, x), z], axis=2)


def fit_hand_geometry(keypoints_world: FloatArray, valid: npt.NDArray[np.bool_], side: Side) -> HandGeometry:
    """Fit the built-in hand to a sequence's own keypoints (medians over valid frames, DESIGN §1.1).

    ``keypoints_world`` (T,21,3) metres, ``valid`` (T,). Palm layout = median of the finger bases in the wrist
    frame; segment lengths = median bone lengths; rest frames as the template's (so hinge angles mean the same
    for every subject); widths = template radii scaled by the fitted hand length.
    """
    kp = np.asarray(keypoints_world, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if kp.ndim != 3 or kp.shape[1:] != (21, 3):
        raise ValueError(f"keypoints_world must have shape (T, 21, 3), got {kp.shape}")
    if valid.shape != (kp.shape[0],):
        raise ValueError(f"valid must have shape ({kp.shape[0]},), got {valid.shape}")
    kp = kp[valid]
    if kp.shape[0] == 0:
        raise SequenceValidationError.single(f"hands[{side}].valid", "no valid frame to fit the hand to")
    rot = wrist_frames(kp, side)
    local = np.einsum("tji,tkj->tki", rot, kp - kp[:, :1])  # R^T (p - wrist)
    bases = np.median(local[:, list(FINGER_BASE_KEYPOINT)], axis=0)
    idx = np.array(FINGER_BASE_KEYPOINT)[:, None] + np.arange(4)[None, :]  # (5,4)
    bones = np.linalg.norm(np.diff(kp[:, idx], axis=2), axis=3)  # (T,5,3)
    lengths = np.median(bones, axis=0)
    m = _mirror(side)
    hand_length = float(np.linalg.norm(bases[2]) + lengths[2].sum())
    s = hand_length / TEMPLATE_HAND_LENGTH
    return HandGeometry(
        side=side,
        bases=bases,
        rest_rot=_rest_frames(bases, _TEMPLATE_THUMB_DIR * m, _TEMPLATE_THUMB_PALMAR * m),
        lengths=lengths,
        radii=_TEMPLATE_RADII * s,
        palm_half_thickness=PALM_HALF_THICKNESS * s,
        scale=s,
        meta={"frames_used": float(kp.shape[0]), "bone_length_mad_mm": float(1e3 * np.median(np.abs(bones - lengths)))},
    )


# ---------------------------------------------------------------------- kinematics


def axis_rotations(axes: FloatArray, angles: FloatArray) -> FloatArray:
    """Rodrigues: rotation matrices (..., 3, 3) about unit ``axes`` (..., 3) by ``angles`` (...)."""
    skew, outer = _rodrigues_parts(axes)
    return _rodrigues(skew, outer, angles)


def _rodrigues_parts(axes: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The angle-free parts of Rodrigues' formula for unit ``axes`` (..., 3): skew matrices and outer products."""
    k = np.zeros((*axes.shape[:-1], 3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -axes[..., 2], axes[..., 1], -axes[..., 0]
    return k - np.swapaxes(k, -1, -2), axes[..., :, None] * axes[..., None, :]


def _rodrigues(skew: FloatArray, outer: FloatArray, angles: FloatArray) -> FloatArray:
    c, s = np.cos(angles)[..., None, None], np.sin(angles)[..., None, None]
    return c * _EYE3 + s * skew + (1 - c) * outer


_EYE3 = np.eye(3)
#: The hinge axes' parts, made once: the retargeting's IK runs the finger kinematics thousands of times a
#: sequence, and rebuilding these for every call was most of its cost (same arithmetic, same bits).
_HINGE_SKEW, _HINGE_OUTER = _rodrigues_parts(AXIS_VECTORS)


@dataclass
class FingerKinematics:
    """Batched finger FK in the wrist frame: ``points`` (B,5,3,3) end of each segment (keypoints base+1..+3),
    ``axes`` (B,5,9,3) hinge axes and ``anchors`` (B,5,9,3) hinge positions, all in the wrist frame."""

    points: FloatArray
    axes: FloatArray
    anchors: FloatArray


def finger_kinematics(geometry: HandGeometry, q: FloatArray) -> FingerKinematics:
    """Forward kinematics of the 5 fingers in the wrist frame for hinge angles ``q`` (B,45)."""
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 45:
        raise ValueError(f"q must have shape (B, 45), got {q.shape}")
    b = q.shape[0]
    qf = q.reshape(b, 5, 9)
    rot = np.broadcast_to(geometry.rest_rot, (b, 5, 3, 3)).copy()
    pos = np.broadcast_to(geometry.bases, (b, 5, 3)).copy()
    points = np.empty((b, 5, 3, 3))
    axes = np.empty((b, 5, 9, 3))
    anchors = np.empty((b, 5, 9, 3))
    for j in range(3):
        for h in range(3):
            k = 3 * j + h
            axes[:, :, k] = rot @ AXIS_VECTORS[h]
            anchors[:, :, k] = pos
            rot = rot @ _rodrigues(_HINGE_SKEW[h], _HINGE_OUTER[h], qf[:, :, k])  # axis_rotations about axis h
        pos = pos + rot[..., 0] * geometry.lengths[:, j, None]
        points[:, :, j] = pos
    return FingerKinematics(points=points, axes=axes, anchors=anchors)


def local_keypoints(geometry: HandGeometry, q: FloatArray) -> FloatArray:
    """(B,21,3) keypoints in the wrist frame for hinge angles ``q`` (B,45)."""
    fk = finger_kinematics(geometry, q)
    b = fk.points.shape[0]
    out = np.zeros((b, 21, 3))
    for f, base in enumerate(FINGER_BASE_KEYPOINT):
        out[:, base] = geometry.bases[f]
        out[:, base + 1 : base + 4] = fk.points[:, f]
    return out




def forward_keypoints(
    geometry: HandGeometry, wrist_pos: FloatArray, wrist_quat: FloatArray, q45: FloatArray
) -> FloatArray:
    """World keypoints of the built-in hand: (21,3) for one pose, or (T,21,3) for batched inputs.

    ``wrist_pos`` (3,) or (T,3); ``wrist_quat`` (4,) or (T,4) wxyz; ``q45`` (45,) or (T,45) in HINGE_NAMES order.
    """
    single = np.ndim(q45) == 1
    q = np.atleast_2d(np.asarray(q45, dtype=np.float64))
    pos = np.atleast_2d(np.asarray(wrist_pos, dtype=np.float64))
    quat = np.atleast_2d(np.asarray(wrist_quat, dtype=np.float64))
    if q.shape[1] != 45 or pos.shape[1] != 3 or quat.shape[1] != 4:
        raise ValueError(
            f"wrist_pos (.,3), wrist_quat (.,4), q45 (.,45) expected; got {pos.shape}, {quat.shape}, {q.shape}"
        )
    local = local_keypoints(geometry, q)
    world = np.einsum("tij,tkj->tki", quat_to_matrix(quat), local) + pos[:, None, :]
    return world[0] if single else world
