"""Helpers (no tests here): a synthetic push whose object motion is, by construction, what a known hand
motion does in simulation (for the refinement's parameter-recovery, determinism and verify tests), and a
grasp-and-lift known answer in the default parameterisation (tests/integration/test_refine_known_answer.py)."""

from __future__ import annotations

from typing import Any

import numpy as np

from common.job_options import JobOptions
from common.sequence import HandTrack, ObjectSpec, Sequence
from worker.hand.model import default_geometry, forward_keypoints

# Palm facing +x (wrist-frame z), fingers up (wrist-frame x = world z): columns are the wrist axes in world.
_PALM_FORWARD = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])


def _quat_from_matrix(rot: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.from_matrix(rot).as_quat(scalar_first=True))


def push_sequence(frames: int = 30, fps: float = 30.0, yaw_deg: float = 0.0, offset_x: float = 0.0,
                  object_pose: np.ndarray | None = None) -> Sequence:
    """A right hand, palm forward, pushing a 6 cm box about 7 cm along +x in one second. Perturbations:
    ``yaw_deg`` turns the hand about the vertical through the wrist, ``offset_x`` shifts its whole path.
    ``object_pose`` (T,7) world; default: the box at rest."""
    from scipy.spatial.transform import Rotation

    geometry = default_geometry("right")
    t = np.arange(frames) / (frames - 1)
    wrist = np.stack([-0.05 + offset_x + 0.08 * t, np.zeros(frames), np.full(frames, 0.004)], axis=1)
    rot = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix() @ _PALM_FORWARD
    quat = np.tile(_quat_from_matrix(rot), (frames, 1))
    keypoints = forward_keypoints(geometry, wrist, quat, np.zeros((frames, 45)))
    if object_pose is None:
        object_pose = np.tile([0.0, 0.0, 0.03, 1.0, 0.0, 0.0, 0.0], (frames, 1))
    return Sequence(
        name=f"synthetic-push-yaw{yaw_deg:g}-dx{offset_x:g}",
        fps=fps,
        object=ObjectSpec(name="box", mass_kg=0.2, primitive="box", size=np.array([0.03, 0.03, 0.03])),
        object_pose=np.asarray(object_pose, dtype=np.float64),
        hands=[HandTrack(side="right", valid=np.ones(frames, dtype=bool), keypoints=keypoints)],
        world_from_source=np.eye(4),
    ).validate()


def recovery_case(frames: int = 30, yaw_deg: float = 0.0, offset_x: float = -0.035) -> tuple[Sequence, np.ndarray]:
    """The object track the unperturbed hand produces in simulation, attached to the perturbed hand."""
    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.prepare import prepare, settled_start
    from worker.refine.replay import replay

    truth = push_sequence(frames)
    prep = prepare(truth, JobOptions())
    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = settled_start(prep, ev)
        rec = replay(prep, ev, start, {s: sp.zero_keyframes() for s, sp in prep.spaces.items()}, False)
    return push_sequence(frames, yaw_deg=yaw_deg, offset_x=offset_x, object_pose=rec.object_pose), rec.object_pose


# ---------------------------------------------------------------------------------------------- known answer
# A known hand motion in the default parameterisation (10 pose coefficients + wrist rotation, no translation):
# the built-in example's grasp, closed further along the pose basis and turned about the grasp centre, which
# lifts the box 20 cm in simulation (the example's own reference does not hold it).
KNOWN_GRIP = np.array([0.2, -1.9, 2.1, -1.1, 0.8, -2.3, 0.3, -0.4, -0.5, -1.4])
KNOWN_TURN = np.array([1.1, 0.1, -0.7])
#: The perturbation of the starting controls: pose coefficients and wrist rotation (the known answer).
KNOWN_POSE_OFFSET = np.array([0.8, -0.6, 0.4, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
KNOWN_ROTATION_OFFSET = np.array([0.6, -0.4, 0.8])
#: The known-answer case is about the control parameterisation, so its box is not held before the hand comes
#: (``SimConfig.hold_until_m``): the truth's hand touches the box one frame after the recorded hand comes within
#: 2 cm of it, so a start turned a few degrees touches it while the hold still welds it, and with the hold this
#: test's seed ends with the wrist further from the truth than it started (x1.15; x0.51 without; issue #15).
KNOWN_ANSWER_SIM: dict[str, Any] = {"hold_until_m": 0.0}


def _rotate_about(points: np.ndarray, pivot: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Rotate (T, ..., 3) points about per-frame pivots (T, 3) by per-frame quaternions (T, 4)."""
    from common.geometry import quat_rotate

    shape = points.shape
    p = points.reshape(shape[0], -1, 3) - pivot[:, None]
    q = np.broadcast_to(quat[:, None], (shape[0], p.shape[1], 4))
    return np.asarray(quat_rotate(q, p) + pivot[:, None]).reshape(shape)


def known_answer_case(options: JobOptions) -> tuple[Sequence, Any, np.ndarray]:
    """(sequence, prepared problem, truth keyframes) of the known-answer test.

    The truth: the grasp-and-lift hand above, whose reference the refinement gets as the recorded keypoints;
    the recorded object is what that hand does in simulation (zero offsets). The start: the control space's
    reference is moved by ``-KNOWN_POSE_OFFSET`` along the pose basis and turned by ``-KNOWN_ROTATION_OFFSET``
    about its pivot, while the loss keeps the recorded targets. Every keyframe equal to
    ``[KNOWN_POSE_OFFSET, KNOWN_ROTATION_OFFSET]`` then gives back the truth's controls (up to the spline's end
    weights and the joint-limit clip), so that is the answer.
    """
    from dataclasses import replace

    from common.geometry import quat_exp, quat_mul
    from worker.example import Timeline, synthetic_grasp_and_lift
    from worker.hand.model import JOINT_LOWER, JOINT_UPPER, forward_keypoints
    from worker.refine.controls import OMEGA_SCALE
    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.prepare import prepare, settled_start
    from worker.refine.replay import replay
    from worker.simulation.config import SimConfig

    clean = synthetic_grasp_and_lift(Timeline(approach=8, close=8, settle=3, lift=14, hold=6), errors=False)
    frames = clean.num_frames
    example = prepare(clean, options, SimConfig(**KNOWN_ANSWER_SIM))
    ref, space = example.references[0], example.spaces["right"]
    ramp = np.clip((np.arange(frames) - 5) / 5.0, 0.0, 1.0)[:, None]  # closing in over frames 5-10
    q = np.clip(ref.q + ramp * (space.basis.stddev * KNOWN_GRIP) @ space.basis.components, JOINT_LOWER, JOINT_UPPER)
    kp = forward_keypoints(ref.geometry, ref.wrist_pos, ref.wrist_quat, q)
    centre = np.einsum("tjk,j->tk", kp, example.hand_targets["right"].joint_weights)
    kp = _rotate_about(kp, centre, quat_exp(OMEGA_SCALE * ramp * KNOWN_TURN))
    hand = HandTrack("right", np.ones(frames, dtype=bool), kp)
    truth = replace(clean, name="known-answer", hands=[hand]).validate()
    prep = prepare(truth, options, SimConfig(**KNOWN_ANSWER_SIM))
    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = settled_start(prep, ev)
        rec = replay(prep, ev, start, {"right": prep.spaces["right"].zero_keyframes()}, False)
    seq = replace(truth, object_pose=rec.object_pose.copy()).validate()
    prep = prepare(seq, options, SimConfig(**KNOWN_ANSWER_SIM))
    s0 = prep.spaces["right"]
    turn = np.broadcast_to(quat_exp(-OMEGA_SCALE * KNOWN_ROTATION_OFFSET), s0.wrist_quat.shape)
    assert s0.pivot is not None
    prep.spaces["right"] = replace(
        s0,
        q_ref=s0.q_ref - (s0.basis.stddev * KNOWN_POSE_OFFSET) @ s0.basis.components,
        wrist_quat=quat_mul(turn, s0.wrist_quat),
        wrist_pos=_rotate_about(s0.wrist_pos, s0.pivot, turn),
    )
    truth_keyframes = np.tile(np.r_[KNOWN_POSE_OFFSET, KNOWN_ROTATION_OFFSET], (s0.n_keyframes, 1))
    return seq, prep, truth_keyframes
