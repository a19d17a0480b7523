"""Refinement losses over recorded simulation arrays (DESIGN §1.5, issue #3 item 2).

Every term is a per-frame quantity summed over the window's frames, made dimensionless by a documented
scale so the default weights read as "how much one scale unit of error costs":

* ``object_pose``: eta * geodesic(R_sim, R_ref) / 0.04 rad + (1 - eta) * ||p_sim - p_ref|| / 1 cm, eta = 0.5
  (2.3 degrees cost as much as 1 cm). The scale trades position for rotation error: on DexYCB dev40 0.1 rad left
  the refined objects at 0.4 cm / 3 degrees, 0.05 at 0.51 cm / 2.51, 0.04 at 0.54 cm / 2.40, against targets of
  0.6 cm and 2.5 degrees (``bench/results/refine_dev.md``).
* ``object_velocity``: ||v_sim - v_ref|| / 0.1 m/s + ||w_sim - w_ref|| / 1 rad/s, the reference from
  central finite differences of the recorded poses.
* ``object_excursion``: (max(0, ||p_sim - p_ref|| - 2 cm) / 0.5 cm)^2 + (max(0, geodesic - 20 deg) / 5 deg)^2: the
  success criterion is a per-frame maximum (every frame within 3 cm and 30 deg), which a sum over frames does
  not protect: a grasp that tracks well but lets the object jump 3 cm for one frame at lift-off scores well on
  ``object_pose`` and still fails. This term is zero while the object stays within 2 cm / 20 deg.
* ``hand_joints``: weighted mean over keypoints of ||k_sim - k_ref|| / 1 cm, fingertips weighted x2
  (frames where the reference hand is valid).
* ``fingertip_contact``: for fingertips that touch the object in the reference (within 1 cm of its surface),
  the distance between the simulated fingertip expressed in the simulated object frame and the reference
  object-local contact point, / 1 cm (averaged over the targets of the frame).
* ``control_consistency``: ||delta(f) - delta(f-1)||^2 in the optimiser's unit-variance coordinates.
* ``hand_velocity``: mean squared hinge velocity / (10 rad/s)^2.
* ``penetration``: (d / 1 mm)^2 with d the hand's deepest penetration into the object at the frame (MuJoCo's
  signed contact distance, ``worker.simulation.scene.penetration_sensor_xml``): soft contacts need some
  penetration to carry a load, so the square lets the shallow contact of a light grip cost little and makes
  the deep ones a hard squeeze or a finger pushed through a thin part leaves (issue #15 item 4) expensive.
  Weight 0.3: on DexYCB dev40's first 20 it took the mean per-frame maximum from 0.68 to 0.45 mm and the
  sequence maxima from 2.12 to 1.24 mm (mean; worst 5.88 -> 2.16) at the same success, E_t +0.01 cm,
  E_r +0.18 deg and x1.04 the time; weight 1 went further (0.32 mm) but cost E_r +0.36 deg. On dev120, the
  sample not tuned on, weight 0.3 improved every figure (paper's protocol: 0.68 -> 0.39 mm, sequence maxima
  2.32 -> 1.47 mm mean, SR 87.5 -> 88.3 %, E_r 4.67 -> 4.14 deg). Charged on every frame, it let a hand that
  has not closed yet keep off the object (the built-in synthetic box lift failed its first attempt: 1 of seeds
  0-2 succeeded); so it is charged only on the frames where the rollout's object is off its rest height
  (``WindowRecord.lifted``, ``PENETRATION_LIFT_M``): the grip forms freely while the object rests and may not
  squeeze through it once it carries the object (seeds 0-2: 3 of 3). On dev120 that gate took success from
  88.3 to 90.8 % (E_r +0.31 deg, nearly all of it one sequence failing either way; penetration unchanged, worst
  sequence maximum 9.3 -> 4.3 mm). A free depth, or charging the recording's lifted frames instead of the
  rollout's, did worse on dev120 (``bench/results/speed_experiments.md``, screen 11).
* ``grasp_reach``: on the frames a hand must hold the object (the recorded object has moved from its start and
  the recorded hand touches it, ``HandKeypointTargets.grip``): the gap between the simulated thumb's distal
  segment and the object's surface, plus the smallest such gap among the other four fingers, each beyond
  ``REACH_TOLERANCE``, / 1 cm. A recorded grasp is often a centimetre open (vision error: the thumb hovers
  over a thin marker); replayed, nothing touches, the object stays on the table and every candidate that
  closes the hand part-way scores the same as one that does not, so CMA-ES has nothing to follow. This term
  is zero for any hand that holds the object with the thumb and one opposing finger. The gaps come from the
  rollout's keypoints (the distal capsules of ``DistalSegments``) and a distance table of the object's surface
  (``distance_grid``), with no extra physics. Weight 3: on the six dev120 sequences whose object was never
  lifted, 0.3 and 1 moved one or two; 3 lifted and held five (one succeeds, four fail on a peak frame). On
  dev120 (paper's protocol): success 90.8 % unchanged (first attempt 85.0 -> 87.5 %), E_t 1.17 -> 0.76 cm, E_r
  4.45 -> 3.38 deg, penetration 0.39 -> 0.46 mm (sequence maxima 1.47 -> 1.69 mm mean, worst 4.3 -> 8.6 mm);
  ``bench/results/left_hands_thin.md``.
* ``robot_joints`` (robot hands only, issue #55): mean over the actuated joints of ((q_sim - q_ret) / 0.1 rad)^2,
  with q_ret the retargeted joint angles: keeps the robot near its retargeted motion in joint space, where
  ``hand_joints`` (the robot's keypoint sites against their retargeted positions) leaves the joints the sites do not
  pin free. Weight 0.1 (``ROBOT_WEIGHTS``).
* ``robot_speed`` (robot hands only): per frame, the sum over the actuated joints of (max(0, |dq| / (v_max / fps)
  - 1) / 0.1)^2 for the simulated joints and for the commanded servo targets, dq their step from the frame before and
  v_max the joint's speed limit (``Embodiment.velocity_limits``; joints without one are not charged): zero while
  the motion stays within the limits a real hand can follow (``worker.robot.metrics``' ratios), one unit for a joint
  10 % over its limit for one frame. The retargeted motion itself is brought within the limits first
  (``worker.robot.speed``); this term keeps the refinement's offsets from speeding it up again. At scale 1 (one unit
  for twice the limit) the refined Allegro commands still ran 7-18 % over the limit on two DexYCB sequences
  (``bench/results/robot_speed_limits.md``). Weight 1 (``ROBOT_WEIGHTS``).

* ``object_articulation`` (an articulated object only, issue #52): per joint |a_sim - a_ref| / 0.04 rad (or / 1 cm
  for a sliding part), the scale of ``object_pose``'s rotation and position parts, plus (max(0, |a_sim - a_ref| -
  10 deg) / 2.5 deg)^2 (2 cm / 5 mm for a sliding part): like ``object_excursion``, a guard for the per-frame
  success limit (15 deg / 3 cm, ``worker.simulation.metrics.SUCCESS_ARTICULATION``) that a sum does not protect.
  With several parts, the contact terms (``fingertip_contact``, ``grasp_reach``) measure each fingertip against the
  part it touches in the recording and each distal segment against the nearest part, in that part's frame.

Each weight can be set to 0 (ablation) through ``JobOptions.loss_weights`` / ``--weights``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from common.geometry import FloatArray, quat_axis_angle, quat_conj, quat_mul, quat_rotate, rotation_angle
from common.job_options import LOSS_NAMES

BoolArray = npt.NDArray[np.bool_]

#: Documented default weights (JobOptions.loss_weights overrides them one by one).
DEFAULT_WEIGHTS: dict[str, float] = {
    "object_pose": 1.0,
    "object_velocity": 0.05,
    "object_excursion": 1.0,
    "hand_joints": 0.3,
    "fingertip_contact": 0.3,
    "control_consistency": 0.05,
    "hand_velocity": 0.01,
    "penetration": 0.3,
    "grasp_reach": 3.0,
    "object_articulation": 1.0,
}
#: Terms only a robot hand has (``HandKeypointTargets.joint_targets``), added to the defaults for one.
ROBOT_WEIGHTS: dict[str, float] = {"robot_joints": 0.1, "robot_speed": 1.0}
assert set(DEFAULT_WEIGHTS) | set(ROBOT_WEIGHTS) == set(LOSS_NAMES)
JOINT_SCALE = 0.1  # rad
SPEED_EXCESS_SCALE = 0.1  # ``robot_speed``: a joint's speed over its limit, as a fraction of the limit

POSE_ETA = 0.5
ROT_SCALE = 0.04  # rad
POS_SCALE = 0.01  # m
LINVEL_SCALE = 0.1  # m/s
ANGVEL_SCALE = 1.0  # rad/s
FINGERTIP_WEIGHT = 2.0
CONTACT_THRESHOLD = 0.01  # m, reference fingertip-to-surface distance that counts as touching
HINGE_VEL_SCALE = 10.0  # rad/s
PENETRATION_SCALE = 0.001  # m
#: The penetration term counts a frame once the rollout's object is this far above its height at the settled
#: start (``WindowRecord.lifted``): above the few millimetres a hand tilting or pushing a resting object lifts it.
PENETRATION_LIFT_M = 0.005
#: Gaps (m) within this count as touching for ``grasp_reach``: the surface points are sampled, the hand's
#: distal segments are capsules (MANO hulls when the hand is MANO's), and soft contacts act slightly apart.
REACH_TOLERANCE = 0.002
#: Gaps beyond this (m) count as this: a hand that has already lost the object in the rollout is not pulled
#: back towards it across the scene (that only bends the hand away from its recording).
REACH_CAP = 0.03
EXCURSION_POS, EXCURSION_POS_SCALE = 0.02, 0.005  # m: free margin, then quadratic per 5 mm
EXCURSION_ROT, EXCURSION_ROT_SCALE = np.radians(20.0), np.radians(5.0)  # rad
#: ``object_articulation``'s scale, free margin and excursion scale per joint kind (rad or m).
ARTICULATION_SCALE = {"revolute": ROT_SCALE, "prismatic": POS_SCALE}
ARTICULATION_MARGIN = {"revolute": (np.radians(10.0), np.radians(2.5)), "prismatic": (0.02, 0.005)}


def resolve_weights(overrides: Mapping[Any, float] | None, robot: bool = False) -> dict[str, float]:
    """The default weights (with ``ROBOT_WEIGHTS`` for a robot hand) with ``overrides`` applied."""
    out = dict(DEFAULT_WEIGHTS) | (ROBOT_WEIGHTS if robot else {})
    for name, value in (overrides or {}).items():
        if name not in out:
            raise ValueError(f"unknown loss weight {name!r}; known: {', '.join(LOSS_NAMES)}")
        if not value >= 0:
            raise ValueError(f"loss weight {name} must be >= 0, got {value}")
        out[name] = float(value)
    return out


def finite_difference_velocity(pos: FloatArray, quat: FloatArray, fps: float) -> FloatArray:
    """(T, 6) world linear and angular velocity of a pose track by central differences."""
    t = pos.shape[0]
    if t < 2:
        return np.zeros((t, 6))
    lin = np.gradient(pos, 1.0 / fps, axis=0)
    # Angular velocity from q(t+1) q(t-1)^-1 over 2 dt (one-sided at the ends).
    nxt = np.r_[np.arange(1, t), t - 1]
    prv = np.r_[0, np.arange(0, t - 1)]
    axis, angle = quat_axis_angle(quat_mul(quat[nxt], quat_conj(quat[prv])))
    span = (nxt - prv) / fps
    ang = axis * (angle / span)[:, None]
    return np.concatenate([lin, ang], axis=1)


@dataclass
class DistalSegments:
    """Each finger's distal segment as the simulated hand builds it (``worker.simulation.hand_mjcf``): a capsule
    from the DIP keypoint towards the fingertip keypoint over ``end_fraction`` of that span, of ``radius``."""

    dip: tuple[int, ...]  # (5,) keypoint indices, thumb first
    tip: tuple[int, ...]  # (5,)
    end_fraction: FloatArray  # (5,)
    radius: FloatArray  # (5,) m

    SAMPLES = 4  # points along each segment's axis

    def gaps(self, keypoints: FloatArray, surface: Callable[[FloatArray], FloatArray]) -> FloatArray:
        """(..., 5) distance of each distal capsule's surface to the object surface, from object-frame keypoints
        (..., J, 3) (negative inside, by up to the radius)."""
        dip = keypoints[..., list(self.dip), :]
        span = keypoints[..., list(self.tip), :] - dip
        s = np.linspace(0.0, 1.0, self.SAMPLES)[:, None] * self.end_fraction[None, :]  # (S, 5)
        points = dip[..., None, :, :] + s[..., None] * span[..., None, :, :]  # (..., S, 5, 3)
        dist = surface(points.reshape(-1, 3)).reshape(points.shape[:-1])
        return np.asarray(dist.min(axis=-2) - self.radius, dtype=np.float64)


@dataclass
class HandKeypointTargets:
    """One hand's reference for the losses."""

    keypoints: FloatArray  # (T, J, 3) world
    valid: BoolArray  # (T,)
    fingertips: tuple[int, ...]  # keypoint indices
    contact_mask: BoolArray  # (T, n_tips) fingertip touches the object in the reference
    contact_local: FloatArray  # (T, n_tips, 3) where, in the object frame
    #: (T,) frames the hand must hold the object (``grasp_reach``); None: the term is off.
    grip: BoolArray | None = None
    distal: DistalSegments | None = None
    #: object-frame points (..., 3) -> distance to the object surface (...,) (``distance_grid.DistanceGrid``)
    surface: Callable[[FloatArray], FloatArray] | None = None
    #: (T, H) the retargeted joint angles of a robot hand (``robot_joints``); None: the human hand.
    joint_targets: FloatArray | None = None
    #: (H,) a robot's joint speed limits as steps per frame (rad; inf: none) and the map from offsets (C, n, dim)
    #: at frames (n,) to its commanded joint targets (C, n, H) (``robot_speed``); None: the term is off.
    step_limits: FloatArray | None = None
    commands: Callable[[FloatArray, npt.NDArray[np.int64]], FloatArray] | None = None
    #: An articulated object: the part each contact target is on (T, n_tips), its parts' surfaces (then
    #: ``contact_local`` is in that part's frame and ``surface`` is unused).
    contact_part: npt.NDArray[np.int64] | None = None
    parts: PartSurfaces | None = None

    def __post_init__(self) -> None:
        t, j, _ = self.keypoints.shape
        n = len(self.fingertips)
        if self.valid.shape != (t,):
            raise ValueError(f"valid must have shape ({t},), got {self.valid.shape}")
        if self.contact_mask.shape != (t, n) or self.contact_local.shape != (t, n, 3):
            raise ValueError(f"contact_mask/contact_local must be ({t}, {n})/({t}, {n}, 3)")
        w = np.ones(j)
        w[list(self.fingertips)] = FINGERTIP_WEIGHT
        self.joint_weights = w / w.sum()


@dataclass
class ObjectTargets:
    pos: FloatArray  # (T, 3) world
    quat: FloatArray  # (T, 4) world wxyz
    vel: FloatArray  # (T, 6) world linear, angular
    #: An articulated object's recorded joint values (T, J) and each joint's kind; None for a rigid one.
    articulation: FloatArray | None = None
    joint_kinds: tuple[str, ...] = ()


@dataclass
class PartSurfaces:
    """An articulated object's parts for the contact terms: per part, object-frame points (..., 3) -> distance to
    its surface (KD-tree, exact) and the same tabulated (``distance_grid``, fast), base first."""

    exact: list[SurfaceDistance]
    fast: list[Callable[[FloatArray], FloatArray]]

    def gaps(self, distal: DistalSegments, keypoints: FloatArray, part_pos: FloatArray, part_quat: FloatArray
             ) -> FloatArray:
        """(..., 5) ``DistalSegments.gaps`` to the nearest part, from world keypoints (..., J, 3) and part poses
        (..., P, 3) / (..., P, 4)."""
        out = None
        for p, surface in enumerate(self.fast):
            local = quat_rotate(quat_conj(part_quat[..., p, None, :]), keypoints - part_pos[..., p, None, :])
            gaps = distal.gaps(local, surface)
            out = gaps if out is None else np.minimum(out, gaps)
        assert out is not None
        return out


def contact_targets(
    keypoints: FloatArray,
    valid: BoolArray,
    obj_pos: FloatArray,
    obj_quat: FloatArray,
    surface_distance: SurfaceDistance,
    fingertips: tuple[int, ...],
    threshold: float = CONTACT_THRESHOLD,
) -> tuple[BoolArray, FloatArray]:
    """Fingertips within ``threshold`` of the object surface in the reference, and their object-local points."""
    tips = keypoints[:, list(fingertips)]  # (T, n, 3)
    local = quat_rotate(quat_conj(obj_quat)[:, None], tips - obj_pos[:, None])
    dist = surface_distance(local.reshape(-1, 3)).reshape(local.shape[:2])
    mask = (dist <= threshold) & valid[:, None]
    return mask, local


def part_contact_targets(
    keypoints: FloatArray,
    valid: BoolArray,
    part_pos: FloatArray,
    part_quat: FloatArray,
    surfaces: list[SurfaceDistance],
    fingertips: tuple[int, ...],
    threshold: float = CONTACT_THRESHOLD,
) -> tuple[BoolArray, FloatArray, npt.NDArray[np.int64]]:
    """``contact_targets`` over an articulated object's parts (T, P, 3) / (T, P, 4): each fingertip's nearest
    part (T, n), whether it is within ``threshold`` of it, and the point in that part's frame."""
    tips = keypoints[:, list(fingertips)]  # (T, n, 3)
    dists, locals_ = [], []
    for p, surface in enumerate(surfaces):
        local = quat_rotate(quat_conj(part_quat[:, p])[:, None], tips - part_pos[:, p, None])
        dists.append(surface(local.reshape(-1, 3)).reshape(local.shape[:2]))
        locals_.append(local)
    dist = np.stack(dists, axis=-1)  # (T, n, P)
    part = np.argmin(dist, axis=-1)
    local = np.take_along_axis(np.stack(locals_, axis=2), part[..., None, None], axis=2)[:, :, 0]
    mask = (np.min(dist, axis=-1) <= threshold) & valid[:, None]
    return mask, local, part.astype(np.int64)


class SurfaceDistance:
    """Unsigned distance of object-frame points to the object surface (vertex-sampled, via a KD-tree)."""

    def __init__(self, surface_points: FloatArray) -> None:
        from scipy.spatial import cKDTree

        self._tree = cKDTree(surface_points)

    def __call__(self, points: FloatArray) -> FloatArray:
        dist, _ = self._tree.query(points)
        return np.asarray(dist, dtype=np.float64)


@dataclass
class WindowRecord:
    """What a batch of C rollouts recorded on the window's frames (F frames)."""

    frames: npt.NDArray[np.int64]  # (F,) sequence frame indices
    obj_pos: FloatArray  # (C, F, 3)
    obj_quat: FloatArray  # (C, F, 4)
    obj_vel: FloatArray  # (C, F, 6) world linear, angular
    keypoints: dict[str, FloatArray]  # side -> (C, F, J, 3)
    hinge_vel: dict[str, FloatArray]  # side -> (C, F, H)
    offsets: dict[str, FloatArray]  # side -> (C, F + 1, dim), delta at frames[0] - 1 .. frames[-1]
    #: side -> (C, F) deepest hand-object penetration (m, >= 0); empty: not recorded (no penetration term)
    penetration: dict[str, FloatArray] = field(default_factory=dict)
    #: (C, F) True where the object is off its rest height in the rollout (the frames the penetration term
    #: counts, ``PENETRATION_LIFT_M``); None: every frame counts.
    lifted: npt.NDArray[np.bool_] | None = None
    #: (F,) factor on the rotation part of ``object_pose`` per frame (``SimWindowProblem.lookahead_rotation_weight``
    #: on the frames a window simulates past the keyframe after the optimised one); None: 1 on every frame.
    rotation_weight: FloatArray | None = None
    #: side -> (C, F, H) actuated joint positions (empty: not recorded; the ``robot_joints`` term reads them)
    joints: dict[str, FloatArray] = field(default_factory=dict)
    #: An articulated object: joint values (C, F, J) and every part's world pose (C, F, P, 3) / (C, F, P, 4), base
    #: first; None for a rigid one.
    articulation: FloatArray | None = None
    part_pos: FloatArray | None = None
    part_quat: FloatArray | None = None


def object_terms(rec: WindowRecord, ref: ObjectTargets) -> dict[str, FloatArray]:
    f = rec.frames
    geo = rotation_angle(rec.obj_quat, ref.quat[f][None])
    dpos = np.linalg.norm(rec.obj_pos - ref.pos[f][None], axis=-1)
    rot = geo if rec.rotation_weight is None else geo * rec.rotation_weight[None]
    pose = POSE_ETA * rot / ROT_SCALE + (1 - POSE_ETA) * dpos / POS_SCALE
    dv = rec.obj_vel - ref.vel[f][None]
    vel = np.linalg.norm(dv[..., :3], axis=-1) / LINVEL_SCALE + np.linalg.norm(dv[..., 3:], axis=-1) / ANGVEL_SCALE
    excursion = (np.maximum(dpos - EXCURSION_POS, 0.0) / EXCURSION_POS_SCALE) ** 2 + (
        np.maximum(geo - EXCURSION_ROT, 0.0) / EXCURSION_ROT_SCALE
    ) ** 2
    out = {
        "object_pose": pose.sum(axis=1),
        "object_velocity": vel.sum(axis=1),
        "object_excursion": excursion.sum(axis=1),
    }
    if rec.articulation is not None and ref.articulation is not None:
        out["object_articulation"] = articulation_term(rec.articulation, ref.articulation[f], ref.joint_kinds)
    return out


def articulation_term(sim: FloatArray, ref: FloatArray, kinds: tuple[str, ...]) -> FloatArray:
    """(C,) ``object_articulation`` of joint values (C, F, J) against the recording's (F, J)."""
    scale = np.array([ARTICULATION_SCALE[k] for k in kinds])
    margin = np.array([ARTICULATION_MARGIN[k][0] for k in kinds])
    margin_scale = np.array([ARTICULATION_MARGIN[k][1] for k in kinds])
    err = np.abs(sim - ref[None])
    return np.asarray((err / scale + (np.maximum(err - margin, 0.0) / margin_scale) ** 2).sum(axis=(1, 2)))


def hand_terms(rec: WindowRecord, side: str, ref: HandKeypointTargets) -> dict[str, FloatArray]:
    f = rec.frames
    kp = rec.keypoints[side]
    valid = ref.valid[f].astype(np.float64)
    err = np.linalg.norm(kp - ref.keypoints[f][None], axis=-1) / POS_SCALE  # (C, F, J)
    joints = (err @ ref.joint_weights * valid).sum(axis=1)
    mask = ref.contact_mask[f]  # (F, n)
    if mask.any():
        tips = kp[:, :, list(ref.fingertips)]
        if ref.contact_part is not None and rec.part_pos is not None and rec.part_quat is not None:
            rows = np.arange(len(f))[:, None]
            part = ref.contact_part[f]  # (F, n): each target's part, whose frame ``contact_local`` is in
            local = quat_rotate(quat_conj(rec.part_quat[:, rows, part]), tips - rec.part_pos[:, rows, part])
        else:
            local = quat_rotate(quat_conj(rec.obj_quat)[:, :, None], tips - rec.obj_pos[:, :, None])
        d = np.linalg.norm(local - ref.contact_local[f][None], axis=-1) / POS_SCALE  # (C, F, n)
        per_frame = (d * mask).sum(axis=2) / np.maximum(mask.sum(axis=1), 1)
        contact = per_frame.sum(axis=1)
    else:
        contact = np.zeros(kp.shape[0])
    offs = rec.offsets[side]
    consistency = (np.diff(offs, axis=1) ** 2).sum(axis=(1, 2))
    hvel = (np.mean(rec.hinge_vel[side] ** 2, axis=2) / HINGE_VEL_SCALE**2).sum(axis=1)
    depth = rec.penetration.get(side)
    if depth is None:
        pen = np.zeros(kp.shape[0])
    else:
        charged = 1.0 if rec.lifted is None else rec.lifted
        pen = ((depth / PENETRATION_SCALE) ** 2 * charged).sum(axis=1)
    reach = np.zeros(kp.shape[0])
    if ref.grip is not None and ref.distal is not None and ref.parts is not None and rec.part_pos is not None:
        grip = ref.grip[f]
        if grip.any():
            assert rec.part_quat is not None
            gaps = ref.parts.gaps(ref.distal, kp[:, grip], rec.part_pos[:, grip], rec.part_quat[:, grip])
            gaps = np.clip(gaps - REACH_TOLERANCE, 0.0, REACH_CAP)  # (C, G, 5)
            reach = ((gaps[..., 0] + gaps[..., 1:].min(axis=-1)) / POS_SCALE).sum(axis=1)
    elif ref.grip is not None and ref.distal is not None and ref.surface is not None:
        grip = ref.grip[f]
        if grip.any():
            pts = kp[:, grip]  # (C, G, J, 3)
            local = quat_rotate(quat_conj(rec.obj_quat[:, grip])[:, :, None], pts - rec.obj_pos[:, grip][:, :, None])
            gaps = np.clip(ref.distal.gaps(local, ref.surface) - REACH_TOLERANCE, 0.0, REACH_CAP)  # (C, G, 5)
            reach = ((gaps[..., 0] + gaps[..., 1:].min(axis=-1)) / POS_SCALE).sum(axis=1)
    out = {
        "hand_joints": joints,
        "fingertip_contact": contact,
        "control_consistency": consistency,
        "hand_velocity": hvel,
        "penetration": pen,
        "grasp_reach": reach,
    }
    if ref.joint_targets is not None and side in rec.joints:
        dq = (rec.joints[side] - ref.joint_targets[f][None]) / JOINT_SCALE
        out["robot_joints"] = (np.mean(dq**2, axis=2) * valid).sum(axis=1)
    if ref.step_limits is not None and ref.commands is not None:
        command = ref.commands(offs, np.r_[f[0] - 1, f])  # (C, F + 1, H)
        out["robot_speed"] = speed_excess(command, ref.step_limits)
        if side in rec.joints:
            out["robot_speed"] = out["robot_speed"] + speed_excess(rec.joints[side], ref.step_limits)
    return out


def speed_excess(q: FloatArray, step_limits: FloatArray) -> FloatArray:
    """(C,) ``robot_speed`` of joint tracks (C, n, H) against steps per frame (H,) (inf: no limit)."""
    over = np.maximum(np.abs(np.diff(q, axis=1)) / step_limits - 1.0, 0.0) / SPEED_EXCESS_SCALE
    return np.asarray((over**2).sum(axis=(1, 2)))


def window_losses(
    rec: WindowRecord,
    obj: ObjectTargets,
    hands: dict[str, HandKeypointTargets],
    weights: dict[str, float],
) -> tuple[dict[str, FloatArray], dict[str, FloatArray]]:
    """Per-hand objectives (C,) (shared object terms + that hand's terms) and the weighted terms (C,).

    Bimanual: each hand's CMA-ES minimises the object terms plus its own hand terms (issue #3 item 7).
    """
    terms = {k: weights[k] * v for k, v in object_terms(rec, obj).items()}
    shared = terms["object_pose"] + terms["object_velocity"] + terms["object_excursion"]
    if "object_articulation" in terms:
        shared = shared + terms["object_articulation"]
    per_hand: dict[str, FloatArray] = {}
    for side, ref in hands.items():
        ht = {k: weights.get(k, 0.0) * v for k, v in hand_terms(rec, side, ref).items()}
        per_hand[side] = shared + sum(ht.values())
        for k, v in ht.items():
            terms[k] = terms.get(k, 0.0) + v
    return per_hand, terms
