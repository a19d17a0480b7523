"""Helpers (no tests here): a synthetic push whose object motion is, by construction, what a known hand
motion does in simulation (for the refinement's parameter-recovery, determinism and verify tests)."""

from __future__ import annotations

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
