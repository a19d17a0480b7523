"""Everything a refinement of one sequence needs before optimising: references, scene, control spaces,
loss targets and the frame-0 state (DESIGN §1.1-1.5). Shared by ``run.refine_sequence`` and ``result.verify``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from common.errors import ConfigurationError
from common.geometry import FloatArray
from common.job_options import JobOptions
from common.primitive_surface import object_surface_points, part_surface_points
from common.sequence import FINGERTIP_INDICES, ObjectSpec, Sequence
from worker.hand.mano.pose import mano_pca_basis
from worker.hand.model import FINGER_BASE_KEYPOINT, MIRROR_SIGNS, HandGeometry
from worker.hand.pose_basis import load_pose_basis
from worker.hand.reference import HandReference
from worker.hand.retarget import retarget_sequence
from worker.refine.controls import HandControlSpace, PoseBasis10
from worker.refine.distance_grid import DistanceGrid
from worker.refine.evaluator import ParallelEvaluator, SimState
from worker.refine.losses import (
    BoolArray,
    DistalSegments,
    HandKeypointTargets,
    ObjectTargets,
    PartSurfaces,
    SurfaceDistance,
    contact_targets,
    finite_difference_velocity,
    part_contact_targets,
)
from worker.refine.problem import SimLayout
from worker.refine.spline import default_keyframe_interval
from worker.robot.basis import robot_basis, robot_distal
from worker.robot.reference import RobotReference
from worker.robot.retarget import robot_references
from worker.simulation.config import SimConfig
from worker.simulation.rest_pose import moved_frame
from worker.simulation.scene import Scene, build_scene
from worker.simulation.stepping import (
    PHYSICS_SPEC,
    HandTargets,
    get_state,
    initial_state,
    lead_track,
    lead_values,
    place_start,
    settle_placed,
)
from worker.simulation.table_fit import TableChoice

#: Defaults chosen for the speed budget (2 shared cores, <= 60 s for 72 frames at 30 fps); see bench/refine.py.
#: 10 generations rather than 6: on dev40 E_t 0.58 -> 0.50 cm and E_r 2.78 -> 2.63 deg for a median of 30 s
#: instead of 21 s per sequence (bench/results/refine_dev.md).
DEFAULT_POPSIZE = 10
DEFAULT_MAX_GENERATIONS = 10
#: What the wrist rotation offset turns the hand about (``controls``): "hand", the centroid of the reference
#: keypoints weighted as the ``hand_joints`` loss weighs them (fingertips x2; the point about which a small
#: rotation moves the keypoints least, and near the centre of a grasp); "wrist", DESIGN §1.3 as written (a held
#: object then swings on the ~8 cm lever from the wrist; results made before the pivot was recorded).
PIVOTS = ("hand", "wrist")
ROTATION_PIVOT = "hand"
#: A left hand's control coordinates are the mirror image of a right hand's (``prepare(mirror_left=...)``): the
#: pose basis with abductions and twists negated, the wrist rotation reflected. Then a sequence and its mirror
#: image are the same problem. Measured on small samples (bench/results/left_hands_thin.md) it did not improve
#: left hands at a small budget (7 of 8 refined a little worse, one more failure); kept because it makes the two
#: sides one method (tests/integration/test_refine_mirror.py). False restores the old treatment of left hands.
MIRROR_LEFT_HAND = True
#: ``config.robot_joint_speed`` of a robot hand's result: whether its retargeted motion was brought within the
#: robot's joint speed limits (``prepare(robot_speed_limits=...)``).
ROBOT_JOINT_SPEED = {True: "within limits", False: "as retargeted"}
#: The grip (``grip_frames``) must have formed this long (s) before the recorded object is seen to move.
GRIP_LEAD_S = 0.1


@dataclass
class Prepared:
    seq: Sequence
    options: JobOptions
    interval: int
    references: list[HandReference] | list[Any]  # RobotReference for a robot hand (``worker.robot``)
    scene: Scene
    layout: SimLayout
    spaces: dict[str, HandControlSpace]
    obj_targets: ObjectTargets
    hand_targets: dict[str, HandKeypointTargets]
    basis_provenance: str
    rotation_pivot: str  # what the wrist rotation offset turns the hand about (one of PIVOTS)
    #: The MANO model folder the references were made with (None: no MANO hand), for the result's MANO arrays.
    mano_dir: Path | None = None
    mirror_left: bool = True  # a left hand's control coordinates mirror a right hand's (``prepare``)
    #: A robot hand's retargeted motion is brought within its joint speed limits (``prepare``).
    robot_speed_limits: bool = True

    @property
    def num_frames(self) -> int:
        return self.seq.num_frames

    def obj_targets_pose(self) -> FloatArray:
        """(T, 7) reference object poses, world x y z qw qx qy qz."""
        return np.concatenate([self.obj_targets.pos, self.obj_targets.quat], axis=1)


def mano_pose_basis(seq: Sequence, reference: HandReference, like: PoseBasis10, mano_dir: Path | None) -> PoseBasis10:
    """MANO's own hand PCA (DESIGN §1.3: "MANO's own PCA when MANO is used"), as hinge changes per unit
    coefficient. Each component is scaled so one unit moves the hinges by as much (RMS) as one unit of the
    built-in basis's component of the same rank, which keeps CMA-ES's step size and bounds meaningful."""
    hand = seq.hand(reference.side)
    assert hand is not None and hand.mano is not None
    mano = mano_pca_basis(mano_dir, reference.side, betas=hand.mano.betas, n_components=10)
    comps = np.asarray(mano.components[:10], dtype=np.float64)
    norms = np.maximum(np.linalg.norm(comps, axis=1), 1e-9)
    builtin_norms = np.linalg.norm(like.components, axis=1) * like.stddev
    return PoseBasis10(comps / norms[:, None], builtin_norms)


def pose_basis(
    references: list[HandReference], seq: Sequence | None = None, mano_dir: Path | None = None,
    mirror_left: bool = True,
) -> tuple[dict[str, PoseBasis10], str]:
    """The packaged pose basis (``worker.hand.pose_basis``, one PCA over the built-in hand's hinges in the right
    hand's convention); a left hand gets its mirror image (``MIRROR_SIGNS``: abductions and twists negated),
    since the left hand that mirrors a right hand at ``q`` is at ``MIRROR_SIGNS * q``. Without the packaged file,
    a PCA of this sequence's own reference hinge angles (a documented fallback named in the provenance).
    ``mirror_left=False``: the packaged basis unmirrored for both sides (results made before issue #15; the
    packaged basis came from right hands only)."""
    try:
        packaged = load_pose_basis()
    except ConfigurationError:
        packaged = None
    if packaged is not None and packaged.components.shape[0] >= 10:
        basis = PoseBasis10(np.asarray(packaged.components[:10], dtype=np.float64),
                            np.asarray(packaged.stddev[:10], dtype=np.float64))
        source = json.dumps(packaged.provenance, sort_keys=True)[:300]
        left = PoseBasis10(basis.components * MIRROR_SIGNS, basis.stddev) if mirror_left else basis
        bases: dict[str, PoseBasis10] = {r.side: left if r.side == "left" else basis for r in references}
        mano_sides = [r.side for r in references if r.from_mano and seq is not None]
        for r in references:
            if r.side in mano_sides:
                assert seq is not None
                bases[r.side] = mano_pose_basis(seq, r, basis, mano_dir)
        if mano_sides:
            source += f"; MANO PCA basis for {', '.join(mano_sides)}"
        if mirror_left and any(r.side == "left" and r.side not in mano_sides for r in references):
            source += "; mirrored for the left hand"
        # A provenance label stored in every result: it keeps the name the basis had when results began to
        # record it (the module now lives in worker.hand), so a result's bytes do not depend on where code sits.
        return bases, f"worker.pose_basis (packaged): {source}"
    out: dict[str, PoseBasis10] = {}
    for r in references:
        q = r.q[r.valid] if r.valid.sum() >= 2 else r.q
        _, sing, vt = np.linalg.svd(q - q.mean(axis=0), full_matrices=False)
        comps = np.zeros((10, 45))
        k = min(10, vt.shape[0])
        comps[:k] = vt[:k]
        std = np.full(10, 0.05)
        std[:k] = np.maximum(sing[:k] / np.sqrt(max(len(q) - 1, 1)), 0.05)
        out[r.side] = PoseBasis10(comps, std)
    return out, "fallback: PCA of this sequence's reference hinge angles (packaged pose basis missing)"


def prepare(
    seq: Sequence,
    options: JobOptions,
    config: SimConfig | None = None,
    rotation_pivot: str | None = None,
    *,
    cache_dir: Path | None = None,
    mano_dir: Path | None = None,
    mirror_left: bool | None = None,
    references: list[HandReference] | list[Any] | None = None,
    robot_speed_limits: bool = True,
    table: TableChoice | None = None,
) -> Prepared:
    """``rotation_pivot``: ``ROTATION_PIVOT`` when None (``verify`` passes the one a result was made with).
    ``cache_dir``: where convex parts are cached (None: memory only); ``mano_dir``: the MANO model folder
    (None: hands given by keypoints only, see ``retarget_sequence``). ``mirror_left``: a left hand's control
    coordinates are the mirror image of a right hand's (pose basis, wrist rotation and translation;
    ``controls``); ``MIRROR_LEFT_HAND`` when None; False reproduces results made before issue #15, which
    recorded no ``config.left_hand_controls``. ``references``: this very sequence's ``retarget_sequence`` output
    when the caller has it already (``derive`` from the refinement, which read the same bytes); retargeting is
    a third of a preparation. ``robot_speed_limits``: a robot hand's retargeted motion is brought within its joint
    speed limits (``worker.robot.speed``); False reproduces robot results made before that
    (``config.robot_joint_speed`` absent). ``table``: a result's stored table choice, stood on instead of the
    fit's own (``build_scene``; ``verify`` and the tools that rebuild a result pass it)."""
    if mirror_left is None:
        mirror_left = MIRROR_LEFT_HAND
    config = config or SimConfig()
    if references is None:
        references = retarget_sequence(seq, mano_dir=mano_dir)
        if options.hand is not None:  # a robot hand: the recorded hand retargeted to it (issue #55)
            references = robot_references(references, options.hand, float(seq.fps) if robot_speed_limits else None)
    scene = build_scene(seq, references, config, cache_dir=cache_dir, table=table)
    layout = SimLayout.from_scene(scene)
    interval = options.keyframe_interval or default_keyframe_interval(seq.fps)
    robots = [r for r in references if isinstance(r, RobotReference)]
    bases: dict[Any, PoseBasis10]
    if robots:
        bases = {r.side: PoseBasis10(*robot_basis(r)) for r in robots}
        provenance = f"robot {robots[0].embodiment.description.name}: PCA of the retargeted joint motion"
    else:
        bases, provenance = pose_basis([r for r in references if isinstance(r, HandReference)], seq, mano_dir,
                                       mirror_left)
    pivot_kind = rotation_pivot or ROTATION_PIVOT
    if pivot_kind not in PIVOTS:
        raise ValueError(f"rotation_pivot must be one of {', '.join(PIVOTS)}, got {pivot_kind!r}")
    pose = seq.object_pose_world()
    obj = ObjectTargets(pose[:, :3], pose[:, 3:], finite_difference_velocity(pose[:, :3], pose[:, 3:], seq.fps))
    hands = (_part_hand_targets(seq, references, pose, obj, config) if seq.object.parts
             else _hand_targets(seq, references, pose, config))  # fmt: skip
    # The mocap and the servo targets run ahead of their tracks by the weld's and the servos' lags
    # (``SimConfig.wrist_lead_s`` / ``finger_lead_s``), as in the raw replay (``stepping.substep_controls``);
    # the pivot moves with the wrist so the hand turns about its centre.
    lead, finger_lead = config.lead_frames(scene.substeps_per_frame)
    spaces: dict[str, HandControlSpace] = {}
    for r in references:
        wrist_pos, wrist_quat = lead_track(r.wrist_pos, r.wrist_quat, lead)
        pivot = pivot_track(pivot_kind, r.keypoints, hands[r.side].joint_weights)
        spaces[r.side] = HandControlSpace(
            side=r.side,
            q_ref=lead_values(r.q, finger_lead),
            wrist_pos=wrist_pos,
            wrist_quat=wrist_quat,
            q_limits=np.asarray(scene.hands[r.side].q_limits, dtype=np.float64),
            basis=bases[r.side],
            interval=interval,
            substeps=scene.substeps_per_frame,
            free_translation=options.free_wrist_translation,
            pivot=None if pivot is None else lead_values(pivot, lead),
            mirrored=mirror_left and r.side == "left",
        )
    for r in robots:  # the ``robot_speed`` term: the commands and joints against the robot's speed limits
        hands[r.side].step_limits = r.embodiment.velocity_limits / float(seq.fps)
        hands[r.side].commands = spaces[r.side].frame_joint_targets
    return Prepared(seq, options, interval, references, scene, layout, spaces, obj, hands, provenance, pivot_kind,
                    mano_dir, mirror_left, robot_speed_limits)


def _hand_targets(
    seq: Sequence, references: list[Any], pose: FloatArray, config: SimConfig
) -> dict[str, HandKeypointTargets]:
    """Each hand's targets against a rigid object."""
    samples = _surface_samples(seq.object, config.primitive_surface_spacing_m)
    surface = SurfaceDistance(samples)
    surface_grid = DistanceGrid(samples)
    hands: dict[str, HandKeypointTargets] = {}
    for r in references:
        tips, distal, joint_targets = _hand_kind(r)
        mask, local = contact_targets(r.keypoints, r.valid, pose[:, :3], pose[:, 3:], surface, tips)
        hands[r.side] = HandKeypointTargets(
            r.keypoints, r.valid, tips, mask, local,
            grip=grip_frames(pose, mask, round(GRIP_LEAD_S * seq.fps)),
            distal=distal, surface=surface_grid, joint_targets=joint_targets,
        )  # fmt: skip
    return hands


def _hand_kind(r: Any) -> tuple[tuple[int, ...], DistalSegments | None, FloatArray | None]:
    """A hand's fingertip keypoints, distal segments and joint targets: the human hand's, or a robot's (its
    fingertip sites, ``robot_distal_segments``, its retargeted joints for ``robot_joints``)."""
    if isinstance(r, RobotReference):
        return r.embodiment.fingertips, robot_distal_segments(r), r.q.copy()
    return FINGERTIP_INDICES, distal_segments(r.geometry), None


def _part_hand_targets(
    seq: Sequence, references: list[Any], pose: FloatArray, obj: ObjectTargets, config: SimConfig
) -> dict[str, HandKeypointTargets]:
    """Each hand's targets against an articulated object: every fingertip's target on the part it touches, in
    that part's frame, and the reach measured to the nearest part (``losses.PartSurfaces``). Fills ``obj``'s
    articulation targets."""
    assert seq.articulation is not None
    obj.articulation = seq.articulation
    obj.joint_kinds = tuple(j.kind for j in seq.object.joints)
    parts = seq.object.part_poses(pose, seq.articulation)  # (T, P, 7)
    samples = [part_surface_points(shape, config.primitive_surface_spacing_m) for shape in seq.object.part_shapes()]
    surfaces = PartSurfaces([SurfaceDistance(s) for s in samples], [DistanceGrid(s) for s in samples])
    hands: dict[str, HandKeypointTargets] = {}
    for r in references:
        tips, distal, joint_targets = _hand_kind(r)
        mask, local, part = part_contact_targets(r.keypoints, r.valid, parts[..., :3], parts[..., 3:],
                                                 surfaces.exact, tips)  # fmt: skip
        # The grip follows the part the hand holds: a hand on a lid grips from when the lid starts to move.
        moved = _part_moved_pose(parts, part, mask)
        hands[r.side] = HandKeypointTargets(
            r.keypoints, r.valid, tips, mask, local,
            grip=grip_frames(moved, mask, round(GRIP_LEAD_S * seq.fps)),
            distal=distal, contact_part=part, parts=surfaces, joint_targets=joint_targets,
        )  # fmt: skip
    return hands


def _part_moved_pose(parts: FloatArray, part: np.ndarray, mask: BoolArray) -> FloatArray:
    """(T, 7) poses of the part a hand touches most in the recording (the base when it touches none)."""
    counts = np.bincount(part[mask], minlength=parts.shape[1]) if mask.any() else np.zeros(parts.shape[1])
    return np.asarray(parts[:, int(np.argmax(counts))])


def grip_frames(object_pose: FloatArray, contact_mask: BoolArray, lead: int = 0) -> BoolArray:
    """(T,) frames a hand must hold the object (``losses.grasp_reach``): from ``lead`` frames before the recorded
    object moves from its start (``rest_pose.moved_frame``: 5 mm or 10 degrees, when it has already started)
    on, where the recorded hand touches it (a fingertip within ``contact_targets``' threshold), so a hand that
    lets go or puts the object down in the recording is not held to it."""
    moved = np.arange(object_pose.shape[0]) >= moved_frame(object_pose) - lead
    return np.asarray(moved & contact_mask.any(axis=1))


def distal_segments(geometry: HandGeometry) -> DistalSegments:
    """The fingers' distal capsules as ``worker.simulation.hand_mjcf`` builds them, in keypoint terms."""
    end = geometry.distal_capsule_ends() / geometry.lengths[:, 2]
    base = np.asarray(FINGER_BASE_KEYPOINT)
    return DistalSegments(tuple(int(b) for b in base + 2), tuple(int(b) for b in base + 3), end,
                          geometry.radii[:, 2].copy())


def robot_distal_segments(ref: RobotReference) -> DistalSegments | None:
    """A robot's fingertip segments for ``grasp_reach`` (``worker.robot.basis.robot_distal``)."""
    found = robot_distal(ref)
    if found is None:
        return None
    dips, tips, radius = found
    return DistalSegments(dips, tips, np.ones(len(tips)), np.full(len(tips), radius))


def pivot_track(kind: str, keypoints: FloatArray, joint_weights: FloatArray) -> FloatArray | None:
    """(T, 3) point the wrist rotation offset turns the hand about (``PIVOTS``; None: the wrist)."""
    if kind == "wrist":
        return None
    return np.asarray(np.einsum("tjk,j->tk", keypoints, joint_weights), dtype=np.float64)


def _surface_samples(shape: ObjectSpec, primitive_spacing: float) -> FloatArray:
    """Object-frame surface points: a mesh's vertices, edge midpoints and face centroids (dense enough for 1 cm);
    a primitive's from ``object_surface_points``."""
    verts = object_surface_points(shape, primitive_spacing)
    faces = shape.mesh_faces
    if faces is None:
        return verts
    tri = verts[faces]
    mids = np.concatenate([(tri[:, 0] + tri[:, 1]) / 2, (tri[:, 1] + tri[:, 2]) / 2, (tri[:, 0] + tri[:, 2]) / 2])
    return np.concatenate([verts, mids, tri.mean(axis=1)])


def settled_start(prep: Prepared, evaluator: ParallelEvaluator) -> tuple[SimState, int]:
    """The settled frame-0 state (``worker.simulation.stepping.initial_state``) with its solver warmstart."""
    data = evaluator.step_data
    physics, steps = initial_state(prep.scene, data, _frame0_targets(prep))
    return SimState(physics.copy(), data.qacc_warmstart.copy()), steps


#: MuJoCo's integration state: everything ``mj_step`` reads, inputs and solver warmstart included.
_INTEGRATION = int(mujoco.mjtState.mjSTATE_INTEGRATION)


def presettle_state(prep: Prepared) -> FloatArray:
    """The integration state the settling of ``settled_start`` starts from (``place_start``): a result stores it so
    that a check on another host settles from the very same bits (``settled_from``)."""
    model = prep.layout.model
    data = mujoco.MjData(model)
    place_start(prep.scene, data, _frame0_targets(prep))
    state = np.empty(mujoco.mj_stateSize(model, _INTEGRATION))
    mujoco.mj_getState(model, data, state, _INTEGRATION)
    return state


def settled_from(prep: Prepared, evaluator: ParallelEvaluator, state: FloatArray) -> SimState:
    """``settled_start``'s settling run from a given pre-settle integration state (``presettle_state``'s)."""
    model, data = prep.layout.model, evaluator.step_data
    mujoco.mj_resetData(model, data)
    mujoco.mj_setState(model, data, np.asarray(state, dtype=np.float64), _INTEGRATION)
    settle_placed(prep.scene, data)
    return SimState(get_state(prep.scene, data, PHYSICS_SPEC).copy(), data.qacc_warmstart.copy())


def _frame0_targets(prep: Prepared) -> dict[str, HandTargets]:
    return {r.side: HandTargets.from_reference(r) for r in prep.references}
