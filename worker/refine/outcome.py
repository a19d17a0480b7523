"""Why a refined result is not executable, from the sequence's own data and its simulation (issue #53 item 2).

``classify_outcome`` reads the prepared problem (the recording, the retargeted hands, the scene) and the refined
replay with its per-frame metrics, and returns the result's ``common.outcome.Outcome``: ``executable`` (success on
the paper's protocol) and, for a result that is not, every reason found, most telling first:

* causes in the recording or the scene: the hand never touches the object (``no_contact``); the recording turns
  or moves the object faster than a grasp can follow at the frames the result fails (``recording_too_fast``);
  the object released as recorded with no hand falls or rolls before the recorded hand reaches it
  (``unsupported_start``); recorded finger keypoints lie deep inside the object's collision geometry
  (``fingers_through_object``); the hand is annotated in too few frames (``hand_sparse``);
* then what the simulated object did: never lifted (``not_lifted``), slipped out of a hand that held it
  (``slipped``), or left the limit for no reason found (``off_track``);
* then informative ones: a recorded step too fast away from the failing frames, ``plan_cut_short``,
  ``rescued_on_finer_parts`` and ``robot_too_fast`` (a robot hand's joints or servo targets beyond its speed
  limits, ``worker.robot.metrics``): the only ones an executable result can carry.

Everything is deterministic and cheap (one object-alone simulation of the approach, forward kinematics of the
recorded poses), so ``verify`` recomputes it. ``tail_cut_reason`` is the check ``worker.refine.run`` makes after a
failed first attempt to skip the rest of its plan.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from common.geometry import FloatArray, quat_axis_angle, quat_conj, quat_mul, quat_to_matrix, rotation_error_deg
from common.outcome import Outcome, OutcomeReason, ReasonCode, Unit
from common.primitive_surface import posed_surface_points
from worker.refine.prepare import Prepared
from worker.simulation.config import CONVEX_DETAILS
from worker.simulation.metrics import (
    LIFT_M,
    PAPER_FIRST_FRAME,
    SUCCESS_POSITION_CM,
    SUCCESS_ROTATION_DEG,
    lifted_frames,
)
from worker.simulation.scene import initial_articulation
from worker.simulation.table_fit import released_motion

#: A recorded object turning faster than this between two frames (at 30 fps; scaled by the frame rate) is a step
#: no grasp follows: 1,350 deg/s (``bench/results/reference_jumps*.md``'s split level). On dev120 and holdout80, 5 of
#: the 7 failures with a larger step fail at it (the other two leave the limit 9-10 frames before it); successes
#: pass steps of 49-65 deg where the simulated object stays within 30 deg on both sides (``bench/results/tail.md``).
#: So the step is a reason only where the result fails at it (``JUMP_REACH_FRAMES``).
TOO_FAST_DEG_AT_30FPS = 45.0
#: The same for the recorded object's translation: 10 cm per frame at 30 fps is 3 m/s, twice the largest step
#: recorded in dev120 and holdout80 (5.7 cm, a clamp lifted fast and refined fine).
TOO_FAST_CM_AT_30FPS = 10.0
#: A step explains a failure when the result is past the limit within this many frames of it, and not before.
JUMP_REACH_FRAMES = 3
#: The first attempt is not followed by the rest of the plan when its failure is explained by a recorded step at
#: least this fast (``tail_cut_reason``). The two successes of dev120 and holdout80 whose first attempt failed
#: with a step above 45 deg (a marker's 49.4 at frame 67, a tuna can's 64.8 at frame 46) failed that attempt 23 and
#: 14 frames before their step, which does not explain it: neither is cut (``bench/results/tail.md``).
TAIL_CUT_DEG_AT_30FPS = TOO_FAST_DEG_AT_30FPS
#: Released on its table with no hand, an object that moves farther than this (cm, or deg) before the recorded
#: hand reaches it is not supported as recorded: resting objects' recordings jitter by less (``rest_pose``:
#: 5 mm, 10 deg), and the table fit's drift of a supported one is a few millimetres.
UNSUPPORTED_CM = 1.0
UNSUPPORTED_DEG = 10.0
#: The recorded hand reaches the object when a keypoint comes this close to its surface.
REACH_M = 0.01
#: A recorded finger keypoint deeper than this inside the collision geometry passes through it. Keypoints are joint
#: centres and fingertips, yet annotation noise puts them up to 21 mm inside the parts in grasps that refine
#: fine (21 dev120 / holdout80 successes of the objects that fail, ``bench/results/tail.md``).
FINGERS_THROUGH_MM = 25.0
#: Recorded finger keypoints inside the convex parts but this far outside the mesh lie in space the parts fill and
#: the object does not (an opening, a handle's loop)...
FILLED_MM = 3.0
#: ... on at least this many keypoint-frames ...
FILLED_MIN = 10
#: ... with the simulated fingertips this far off their recording there on average: the parts hold the hand off
#: (the pitcher base whose handle opening they fill is held 2-3.5 cm off, ``refine_holdout80.md``). Filled space
#: alone is not enough: a pitcher-base success has as much (47 keypoint-frames past 3 mm, ``bench/results/tail.md``).
HELD_OFF_CM = 2.0
#: Surface samples of a mesh for the side of its surface a point lies on.
MESH_SAMPLES = 40_000
#: Fewer annotated frames than this share of the sequence (per hand) is too few to drive the hand along.
HAND_SPARSE_SHARE = 0.5
#: The simulated object slipped when a hand touched it within this many frames before it first left the limit.
SLIP_FRAMES = 5


@dataclass(frozen=True)
class PlanCut:
    """Why and where the refinement stopped before its whole plan ran (``worker.refine.run``)."""

    evaluations: int  # candidate evaluations spent
    why: str  # "recording" (a reason says no grasp follows) or "budget" (the evaluation budget)


def classify_outcome(
    prep: Prepared, refined: dict[str, Any], object_pose_sim: FloatArray, *, hand_contact: np.ndarray | None,
    rescued: bool = False, cut: PlanCut | None = None, cache_dir: Path | None = None,
) -> Outcome:
    """The outcome of a refined replay: ``refined`` its ``compute_metrics`` output (with ``per_frame``),
    ``object_pose_sim`` (F, 7) its simulated object, ``hand_contact`` (F,) whether a hand touched the object in
    each frame (None: not recorded), ``rescued``
    whether it was kept on the finer convex parts, ``cut`` whether the plan was cut short. ``cache_dir``: the
    convex parts' cache (``prepare``)."""
    executable = bool(refined["paper"]["success"])
    reasons: list[OutcomeReason] = []
    if not executable:
        reasons = failure_reasons(prep, refined, object_pose_sim, hand_contact, cache_dir)
    if cut is not None:
        reasons.append(_cut_reason(cut))
    if rescued:
        reasons.append(OutcomeReason(code=ReasonCode.RESCUED_ON_FINER_PARTS,
                                     message="Every attempt on the object's convex parts failed; this result was "
                                             "reached on its finer convex parts."))
    reasons += robot_too_fast(refined)
    return Outcome(executable=executable, reasons=reasons)


def robot_too_fast(refined: dict[str, Any]) -> list[OutcomeReason]:
    """``robot_too_fast`` for each robot hand whose joints or commands exceed its speed limits (``refined``'s
    ``robot`` metrics; none for the human hand)."""
    out = []
    for side, m in sorted((refined.get("robot") or {}).items()):
        if not m.get("speed_limit_exceeded"):
            continue
        sim, command = m["velocity_ratio"], m["command_velocity_ratio"]
        out.append(OutcomeReason(
            code=ReasonCode.ROBOT_TOO_FAST, frame=m.get("speed_limit_frame"), value=round(max(sim, command), 3),
            unit="ratio", message=f"The {side} robot hand's joints move at up to {sim:.2f}x its joint speed limit "
                                  f"(servo targets {command:.2f}x): the real hand cannot follow this motion."))
    return out


def was_rescued(prep: Prepared) -> bool:
    """Whether a result made on ``prep`` is the rescue's (its convex parts are the finer ones)."""
    return prep.scene.config.convex_detail != CONVEX_DETAILS[0]


def failure_reasons(
    prep: Prepared, refined: dict[str, Any], object_pose_sim: FloatArray, hand_contact: np.ndarray | None,
    cache_dir: Path | None = None,
) -> list[OutcomeReason]:
    """Every reason a non-executable replay fails, most telling first (see the module docstring)."""
    per_frame = refined["per_frame"]
    fail = first_past_limit(per_frame)
    touched = np.zeros(prep.num_frames, dtype=bool) if hand_contact is None else np.asarray(hand_contact, bool)
    causes: list[OutcomeReason] = []
    later: list[OutcomeReason] = []
    if hand_contact is not None and not touched.any():
        causes.append(_no_contact(prep))
    fast = recording_too_fast(prep, per_frame)
    if fast is not None:
        (causes if _explains(fast, per_frame, fail) else later).append(fast)
    for check in (unsupported_start(prep, cache_dir), fingers_through_object(prep, per_frame),
                  hand_sparse(prep)):
        if check is not None:
            causes.append(check)
    causes.append(_what_happened(prep, per_frame, object_pose_sim, fail, touched))
    return causes + later


# ------------------------------------------------------------------------------------------- the limit


def past_limit(per_frame: dict[str, np.ndarray]) -> np.ndarray:
    """(F,) frames the paper's protocol counts whose object (or joint) error is past the success limit."""
    bad = (per_frame["e_t_cm"] > SUCCESS_POSITION_CM) | (per_frame["e_r_deg"] > SUCCESS_ROTATION_DEG)
    if "a_ok" in per_frame:
        bad |= per_frame["a_ok"] <= 0
    bad &= np.arange(bad.shape[0]) >= PAPER_FIRST_FRAME
    return np.asarray(bad)


def first_past_limit(per_frame: dict[str, np.ndarray]) -> int | None:
    """The first frame past the limit (None: none)."""
    bad = np.nonzero(past_limit(per_frame))[0]
    return int(bad[0]) if bad.size else None


def _limit_error(per_frame: dict[str, np.ndarray], frame: int) -> tuple[float, Unit]:
    """The error that breaks the limit at ``frame``, in its unit: position (cm), rotation or joint (deg)."""
    e_t, e_r = float(per_frame["e_t_cm"][frame]), float(per_frame["e_r_deg"][frame])
    if e_t > SUCCESS_POSITION_CM:
        return e_t, "cm"
    if e_r > SUCCESS_ROTATION_DEG or "e_a" not in per_frame:
        return e_r, "deg"
    return float(per_frame["e_a"][frame]), "deg"


# ------------------------------------------------------------------------------------------- the recording


def recording_steps(pose: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(F-1,) the recorded object's rotation (deg) and translation (cm) between consecutive frames."""
    _, angle = quat_axis_angle(quat_mul(quat_conj(pose[:-1, 3:]), pose[1:, 3:]))
    return np.degrees(angle), 100.0 * np.linalg.norm(np.diff(pose[:, :3], axis=0), axis=1)


def recording_too_fast(prep: Prepared, per_frame: dict[str, np.ndarray] | None = None,
                       deg_at_30fps: float = TOO_FAST_DEG_AT_30FPS) -> OutcomeReason | None:
    """The recording's fastest step, when it is beyond what a grasp follows (rotation first, then translation)
    among the frames the paper's protocol counts; frame: the later of the two."""
    pose = prep.obj_targets_pose()
    if pose.shape[0] < 2:
        return None
    deg, cm = recording_steps(pose)
    counted = np.arange(1, pose.shape[0]) >= PAPER_FIRST_FRAME
    deg, cm = np.where(counted, deg, 0.0), np.where(counted, cm, 0.0)
    rate = 30.0 / float(prep.seq.fps)
    k = int(np.argmax(deg))
    if deg[k] > deg_at_30fps * rate:
        return OutcomeReason(code=ReasonCode.RECORDING_TOO_FAST, frame=k + 1, value=round(float(deg[k]), 2),
                             unit="deg/frame",
                             message=f"The recorded object turns {deg[k]:.0f} deg between frames {k} and {k + 1}, "
                                     f"faster than any grasp can follow.")
    k = int(np.argmax(cm))
    if cm[k] > TOO_FAST_CM_AT_30FPS * rate:
        return OutcomeReason(code=ReasonCode.RECORDING_TOO_FAST, frame=k + 1, value=round(float(cm[k]), 2),
                             unit="cm/frame",
                             message=f"The recorded object moves {cm[k]:.1f} cm between frames {k} and {k + 1}, "
                                     f"faster than any grasp can follow.")
    return None


def _explains(fast: OutcomeReason, per_frame: dict[str, np.ndarray], fail: int | None) -> bool:
    """Whether a recorded step explains the failure: the result is past the limit near it and not long before."""
    assert fast.frame is not None
    if fail is None or fail < fast.frame - JUMP_REACH_FRAMES:
        return False
    bad = np.nonzero(past_limit(per_frame))[0]
    return bool(np.any(np.abs(bad - fast.frame) <= JUMP_REACH_FRAMES))


def tail_cut_reason(prep: Prepared, metrics: dict[str, Any]) -> OutcomeReason | None:
    """The reason a failed attempt's replay (``metrics``: ``compute_metrics`` with ``per_frame``) says no grasp
    can follow the recording, so the rest of the plan would be spent in vain: a recorded step at least
    ``TAIL_CUT_DEG_AT_30FPS`` fast that explains where it fails. None when it succeeded or nothing says so."""
    if metrics["paper"]["success"]:
        return None
    per_frame = metrics["per_frame"]
    fast = recording_too_fast(prep, per_frame, TAIL_CUT_DEG_AT_30FPS)
    if fast is None or fast.unit != "deg/frame" or not _explains(fast, per_frame, first_past_limit(per_frame)):
        return None
    return fast


def _cut_reason(cut: PlanCut) -> OutcomeReason:
    why = ("the first attempt failed at a recorded step no grasp can follow" if cut.why == "recording"
           else "its evaluation budget was spent")
    return OutcomeReason(code=ReasonCode.PLAN_CUT_SHORT, value=float(cut.evaluations), unit="evaluations",
                         message=f"The refinement stopped after {cut.evaluations} candidate evaluations, before its "
                                 f"whole plan ran: {why}.")


def hand_sparse(prep: Prepared) -> OutcomeReason | None:
    """The least-annotated hand, when it is annotated in fewer than ``HAND_SPARSE_SHARE`` of the frames; frame:
    the first frame of its longest unannotated gap."""
    worst: tuple[float, int] | None = None
    for ref in prep.references:
        valid = np.asarray(ref.valid, dtype=bool)
        share = float(valid.mean()) if valid.size else 0.0
        if worst is None or share < worst[0]:
            worst = (share, _longest_gap_start(valid))
    if worst is None or worst[0] >= HAND_SPARSE_SHARE:
        return None
    share, gap = worst
    return OutcomeReason(code=ReasonCode.HAND_SPARSE, frame=gap, value=round(share, 3), unit="fraction",
                         message=f"The hand is annotated in only {100 * share:.0f} % of the frames (the longest "
                                 f"gap starts at frame {gap}).")


def _longest_gap_start(valid: np.ndarray) -> int:
    best, best_len, start = 0, 0, None
    for i, ok in enumerate([*valid.tolist(), True]):
        if not ok and start is None:
            start = i
        elif ok and start is not None:
            if i - start > best_len:
                best, best_len = start, i - start
            start = None
    return best


# ------------------------------------------------------------------------------------------- the scene


def _recorded_keypoints(prep: Prepared) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per hand, the recorded keypoints (F, K, 3; a robot hand's human ones) and the frames they are valid."""
    out = []
    for ref in prep.references:
        kp = getattr(ref, "human_keypoints", None)
        out.append((np.asarray(ref.keypoints if kp is None else kp), np.asarray(ref.valid, dtype=bool)))
    return out


def _to_object_frame(pose: FloatArray, points: FloatArray) -> FloatArray:
    """(F, K, 3) world points in each frame's object frame ((F, 7) poses)."""
    rots = np.stack([quat_to_matrix(q) for q in pose[:, 3:]])
    return np.asarray(np.einsum("tji,tkj->tki", rots, points - pose[:, None, :3]), dtype=np.float64)


def _surface_distance(prep: Prepared) -> tuple[FloatArray, FloatArray]:
    """(F,) per frame the closest valid recorded keypoint's distance to the object's surface (m; inf where no
    hand is valid), and the object's surface points (object frame)."""
    surface = posed_surface_points(prep.seq.object, initial_articulation(prep.seq), 0.005)
    tree = cKDTree(surface)
    pose = prep.obj_targets_pose()
    closest = np.full(pose.shape[0], np.inf)
    for kp, valid in _recorded_keypoints(prep):
        dist, _ = tree.query(_to_object_frame(pose, kp).reshape(-1, 3))
        per = dist.reshape(pose.shape[0], -1).min(axis=1)
        closest = np.minimum(closest, np.where(valid, per, np.inf))
    return closest, surface


def _no_contact(prep: Prepared) -> OutcomeReason:
    closest, _ = _surface_distance(prep)
    k = int(np.argmin(closest))
    cm = 100.0 * float(closest[k]) if np.isfinite(closest[k]) else None
    near = "" if cm is None else f"; the recorded hand comes within {cm:.1f} cm of it at frame {k}"
    return OutcomeReason(code=ReasonCode.NO_CONTACT, frame=k if cm is not None else None,
                         value=None if cm is None else round(cm, 2), unit="cm",
                         message=f"The simulated hand never touches the object{near}.")


def unsupported_start(prep: Prepared, cache_dir: Path | None = None) -> OutcomeReason | None:
    """Release the object where it starts, on its table, with no hand: when it falls or rolls farther than
    ``UNSUPPORTED_CM`` / ``UNSUPPORTED_DEG`` before the recorded hand first reaches it (``REACH_M``), how far it
    had gone by then, and the frame it first went past that."""
    closest, _ = _surface_distance(prep)
    reached = np.nonzero(closest < REACH_M)[0]
    contact = int(reached[0]) if reached.size else prep.num_frames - 1
    if contact < 1:
        return None
    scene = prep.scene
    arti0 = initial_articulation(prep.seq)
    motion = released_motion(prep.seq, scene.config, scene.object_init_pose, scene.table, contact,
                             cache_dir=cache_dir, articulation=arti0)
    moved_cm = 100.0 * np.linalg.norm(motion[:, :3] - motion[0, :3], axis=1)
    turned = rotation_error_deg(motion[:, 3:], np.repeat(motion[:1, 3:], len(motion), axis=0))
    away = np.nonzero((moved_cm > UNSUPPORTED_CM) | (turned > UNSUPPORTED_DEG))[0]
    if not away.size:
        return None
    first = int(away[0])
    if moved_cm[-1] > UNSUPPORTED_CM:
        value, unit, what = float(moved_cm[-1]), "cm", f"falls or slides {moved_cm[-1]:.1f} cm"
    else:
        value, unit, what = float(turned[-1]), "deg", f"tips or rolls {turned[-1]:.0f} deg"
    return OutcomeReason(code=ReasonCode.UNSUPPORTED_START, frame=first, value=round(value, 2), unit=unit,
                         message=f"Released as recorded with no hand, the object {what} before the recorded hand "
                                 f"reaches it at frame {contact} (it is past {UNSUPPORTED_CM:g} cm / "
                                 f"{UNSUPPORTED_DEG:g} deg from frame {first}): something the scene lacks supports "
                                 f"it.")


def fingers_through_object(prep: Prepared, per_frame: dict[str, np.ndarray] | None = None) -> OutcomeReason | None:
    """Recorded finger keypoints where the simulated object is solid but the real one is not: deeper than
    ``FINGERS_THROUGH_MM`` inside its collision geometry at the recorded pose, or (a mesh object) in space its
    convex parts fill beyond the mesh's surface (an opening, a handle's loop) by more than ``FILLED_MM`` on at
    least ``FILLED_MIN`` keypoint-frames while the simulated fingertips are held off their recording by more than
    ``HELD_OFF_CM`` there (``per_frame``: the replay's ``e_ft_cm``). Value: that depth (mm), frame: where."""
    inside = finger_depths(prep)
    if inside is None:
        return None
    depth, outside, valid = inside
    deep = np.where(valid, depth, 0.0)
    f, _ = np.unravel_index(int(np.argmax(deep)), deep.shape)
    if deep[f].max() * 1000.0 > FINGERS_THROUGH_MM:
        mm = float(deep[f].max()) * 1000.0
        return OutcomeReason(code=ReasonCode.FINGERS_THROUGH_OBJECT, frame=int(f), value=round(mm, 1), unit="mm",
                             message=f"The recorded fingers lie {mm:.0f} mm deep inside the object's simulated "
                                     f"geometry at frame {f}: the recorded grasp cannot be reproduced.")
    if outside is None or per_frame is None:
        return None
    filled = (depth > 0) & (outside > FILLED_MM / 1000.0) & valid
    frames = np.nonzero(filled.any(axis=1))[0]
    if filled.sum() < FILLED_MIN or not frames.size:
        return None
    held_off = float(np.nanmean(per_frame["e_ft_cm"][frames]))
    if not held_off > HELD_OFF_CM:
        return None
    gap = np.where(filled, outside, 0.0)
    at = int(np.argmax(gap.max(axis=1)))
    mm = float(gap[at].max()) * 1000.0
    return OutcomeReason(code=ReasonCode.FINGERS_THROUGH_OBJECT, frame=at, value=round(mm, 1), unit="mm",
                         message=f"The recorded fingers pass through space the object's convex parts fill but the "
                                 f"object does not (up to {mm:.0f} mm beyond its surface, frames {frames[0]}-"
                                 f"{frames[-1]}, e.g. a handle's opening); the simulated fingertips are held "
                                 f"{held_off:.1f} cm off the recording there.")


def recorded_depth(prep: Prepared) -> tuple[float, int]:
    """(mm, frame) the deepest a valid recorded finger keypoint (not the wrist) lies inside the object's base-part
    collision geoms at the recorded object pose; (0, 0) when none is inside."""
    inside = finger_depths(prep)
    if inside is None:
        return 0.0, 0
    depth = np.where(inside[2], inside[0], 0.0)
    f, _ = np.unravel_index(int(np.argmax(depth)), depth.shape)
    return max(0.0, 1000.0 * float(depth[f].max())), int(f)


def finger_depths(prep: Prepared) -> tuple[np.ndarray, np.ndarray | None, np.ndarray] | None:
    """For every hand's finger keypoints (not the wrist, which lies inside the palm) at the recorded object pose:
    (F, K) depth inside the base part's collision geoms (m, positive inside), (F, K) signed distance outside the
    object's mesh (m; None for a primitive or articulated object), (F, K) whether its hand is annotated (several
    hands: concatenated along K)."""
    scene = prep.scene
    model = scene.model
    base = [int(g) for g in scene.object_geom_ids if int(scene.geom_part[g]) <= 0]
    if not base:
        return None
    shapes = [_GeomShape.of(model, g) for g in base]
    pose = prep.obj_targets_pose()
    obj = prep.seq.object
    mesh = None if obj.parts or obj.mesh_vertices is None or obj.mesh_faces is None else _MeshSide.of(obj)
    depths, outsides, valids = [], [], []
    for kp, valid in _recorded_keypoints(prep):
        local = _to_object_frame(pose, kp[:, 1:])
        depths.append(np.max([sh.depth(local, model, scene.object_body_id) for sh in shapes], axis=0))
        if mesh is not None:
            outsides.append(mesh.outside(local))
        valids.append(np.repeat(valid[:, None], local.shape[1], axis=1))
    return (np.concatenate(depths, axis=1), np.concatenate(outsides, axis=1) if mesh is not None else None,
            np.concatenate(valids, axis=1))


@dataclass
class _MeshSide:
    """Which side of a mesh's surface points lie: dense surface samples with their faces' outward normals."""

    tree: cKDTree
    points: np.ndarray
    normals: np.ndarray

    @classmethod
    def of(cls, obj: Any) -> _MeshSide:
        import trimesh

        mesh = trimesh.Trimesh(np.asarray(obj.mesh_vertices), np.asarray(obj.mesh_faces), process=False)
        points, faces = trimesh.sample.sample_surface(mesh, MESH_SAMPLES, seed=0)
        points = np.asarray(points, dtype=np.float64)
        return cls(cKDTree(points), points, np.asarray(mesh.face_normals[faces], dtype=np.float64))

    def outside(self, points: np.ndarray) -> np.ndarray:
        """(...) signed distance of (..., 3) points to the surface (m; positive outside, by the nearest sample's
        normal)."""
        flat = points.reshape(-1, 3)
        dist, i = self.tree.query(flat)
        sign = np.sign(np.einsum("ij,ij->i", flat - self.points[i], self.normals[i]))
        return np.asarray((sign * dist).reshape(points.shape[:-1]))


@dataclass
class _GeomShape:
    """One collision geom, for the depth of points inside it (m, positive inside)."""

    geom: int
    kind: int
    size: np.ndarray
    planes: np.ndarray | None = None  # a mesh's hull: (P, 4) outward unit normals and offsets, geom frame

    @classmethod
    def of(cls, model: mujoco.MjModel, g: int) -> _GeomShape:
        kind = int(model.geom_type[g])
        planes = None
        if kind == mujoco.mjtGeom.mjGEOM_MESH:
            m = int(model.geom_dataid[g])
            a, n = int(model.mesh_vertadr[m]), int(model.mesh_vertnum[m])
            planes = ConvexHull(np.asarray(model.mesh_vert[a : a + n], dtype=np.float64)).equations
        return cls(g, kind, np.asarray(model.geom_size[g], dtype=np.float64), planes)

    def depth(self, points_body: np.ndarray, model: mujoco.MjModel, body: int) -> np.ndarray:
        """(F, K) depth of points given in the object body's frame (the recorded pose's frame)."""
        rot = quat_to_matrix(np.asarray(model.geom_quat[self.geom]))
        p = (points_body - model.geom_pos[self.geom]) @ rot  # geom frame
        s = self.size
        if self.planes is not None:
            return np.asarray(-(p @ self.planes[:, :3].T + self.planes[:, 3]).max(axis=-1))
        if self.kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            return np.asarray(s[0] - np.linalg.norm(p, axis=-1))
        if self.kind == mujoco.mjtGeom.mjGEOM_BOX:
            return np.asarray((s - np.abs(p)).min(axis=-1))
        if self.kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
            return np.asarray(np.minimum(s[0] - np.linalg.norm(p[..., :2], axis=-1), s[1] - np.abs(p[..., 2])))
        if self.kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
            z = np.clip(p[..., 2], -s[1], s[1])
            return np.asarray(s[0] - np.linalg.norm(p - np.stack([0 * z, 0 * z, z], axis=-1), axis=-1))
        return np.zeros(p.shape[:-1])


# ------------------------------------------------------------------------------------------- what happened


def _what_happened(prep: Prepared, per_frame: dict[str, np.ndarray], object_pose_sim: FloatArray, fail: int | None,
                   touched: np.ndarray) -> OutcomeReason:
    """``not_lifted``, ``slipped`` or ``off_track`` at the first frame past the limit."""
    if fail is None:  # not executable on the paper's protocol without a frame past its limit: cannot happen
        return OutcomeReason(code=ReasonCode.OFF_TRACK, message="The object leaves the success limit.")
    value, unit = _limit_error(per_frame, fail)
    ref = prep.obj_targets_pose()
    lifted = lifted_frames(ref)
    if touched.any() and lifted.any():
        rise = 100.0 * float((object_pose_sim[lifted, 2] - object_pose_sim[0, 2]).max())
        if rise < 100.0 * LIFT_M:
            return OutcomeReason(code=ReasonCode.NOT_LIFTED, frame=fail, value=round(rise, 2), unit="cm",
                                 message=f"The hand touches the object but never lifts it: it rises at most "
                                         f"{rise:.1f} cm while the recording lifts it (past the limit from frame "
                                         f"{fail}).")
    if touched[max(0, fail - SLIP_FRAMES) : fail + 1].any():
        return OutcomeReason(code=ReasonCode.SLIPPED, frame=fail, value=round(value, 2), unit=unit,
                             message=f"The object slips in the grasp: {value:.1f} {unit} off the recording at frame "
                                     f"{fail}, the first past the 3 cm / 30 deg limit.")
    return OutcomeReason(code=ReasonCode.OFF_TRACK, frame=fail, value=round(value, 2), unit=unit,
                         message=f"The object is {value:.1f} {unit} off the recording at frame {fail}, the first "
                                 f"past the 3 cm / 30 deg limit, with no hand touching it.")

