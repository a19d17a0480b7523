"""The reference a hand is driven along: its wrist track and hinge angles per frame, on the built-in hand
(retargeted by IK, ``retarget``) or on the subject's MANO hand (``mano.pose``).

Its own module, below both producers, so neither imports the other for the type.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from common.geometry import FloatArray
from common.sequence import Side
from worker.hand.model import HandGeometry, forward_keypoints


@dataclass
class HandReference:
    """The retargeted reference of one hand (world frame, T frames).

    ``wrist_pos`` (T,3), ``wrist_quat`` (T,4) wxyz (sign-continuous), ``q`` (T,45) hinge angles in HINGE_NAMES
    order, ``keypoints`` (T,21,3) the target keypoints (observed where valid, the fitted hand's where
    interpolated), ``valid`` (T,), ``residual_mm`` (T,) mean keypoint distance of the fit (NaN where invalid).
    ``from_mano``: the hand is the subject's MANO hand posed from MANO parameters (results then also carry
    ``S_mano_*`` parameters, ``worker.hand.mano.pose.mano_result_arrays``).
    """

    side: Side
    geometry: HandGeometry
    wrist_pos: FloatArray
    wrist_quat: FloatArray
    q: FloatArray
    keypoints: FloatArray
    valid: npt.NDArray[np.bool_]
    residual_mm: FloatArray
    from_mano: bool = False

    @property
    def num_frames(self) -> int:
        return int(self.q.shape[0])

    def mean_residual_mm(self) -> float:
        return float(np.nanmean(self.residual_mm)) if self.valid.any() else float("nan")

    def fitted_keypoints(self) -> FloatArray:
        """(T,21,3) keypoints of the built-in hand at the reference pose."""
        return forward_keypoints(self.geometry, self.wrist_pos, self.wrist_quat, self.q)
