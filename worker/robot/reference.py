"""A robot hand's reference: the retargeted motion it is driven along (``worker.robot.retarget``), the robot's
counterpart of ``worker.hand.reference.HandReference``.

``wrist_pos`` / ``wrist_quat`` (T, 3) / (T, 4) are the root body's track, ``q`` (T, H) the actuated joints,
``keypoints`` (T, J, 3) the robot's keypoint sites on the retargeted motion (the targets the refinement keeps it
near: ``hand_joints`` loss, fingertip contacts, E_j / E_ft), ``human_keypoints`` (T, J, 3) the recorded human
keypoints they were retargeted to, ``valid`` (T,) where the recorded hand was seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from common.geometry import FloatArray
from common.sequence import Side
from worker.robot.embodiment import Embodiment
from worker.robot.fragment import robot_fragment
from worker.simulation.config import SimConfig
from worker.simulation.hand_fragment import HandFragment


@dataclass
class RobotReference:
    """See the module docstring."""

    side: Side
    embodiment: Embodiment
    wrist_pos: FloatArray
    wrist_quat: FloatArray
    q: FloatArray
    keypoints: FloatArray
    human_keypoints: FloatArray
    valid: npt.NDArray[np.bool_]
    from_mano = False

    @property
    def num_frames(self) -> int:
        return int(self.q.shape[0])

    def fragment(self, config: SimConfig) -> HandFragment:
        """The robot's scene fragment at the reference's frame-0 root pose."""
        return robot_fragment(self.embodiment, config, self.wrist_pos[0], self.wrist_quat[0])

    def residual_mm(self) -> FloatArray:
        """(T,) mean distance of the retargeted sites to the human keypoints they follow (mm)."""
        return np.asarray(1000.0 * np.linalg.norm(self.keypoints - self.human_keypoints, axis=-1).mean(axis=1))

    def mean_residual_mm(self) -> float:
        """``residual_mm`` over the frames where the hand is annotated (as ``HandReference.mean_residual_mm``)."""
        return float(np.mean(self.residual_mm()[self.valid])) if self.valid.any() else float("nan")

    def fingertip_residual_mm(self) -> FloatArray:
        """(T,) mean over the fingertips of the same (mm)."""
        tips = list(self.embodiment.fingertips)
        diff = self.keypoints[:, tips] - self.human_keypoints[:, tips]
        return np.asarray(1000.0 * np.linalg.norm(diff, axis=-1).mean(axis=1))
