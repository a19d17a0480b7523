"""Tracking metrics (DESIGN §1.8, as in the paper and ManipTrans).

* E_t (cm): mean over frames of the object position error;
* E_r (deg): mean over frames of the geodesic angle between simulated and reference object rotations;
* E_j (cm): mean over valid frames and all 21 joints of the hand keypoint error (all hands pooled);
* E_ft (cm): the same over the 5 fingertips;
* success: every frame has position error <= 3 cm and rotation error <= 30 deg.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from common.geometry import FloatArray, rotation_error_deg
from common.sequence import FINGERTIP_INDICES

SUCCESS_POSITION_CM = 3.0
SUCCESS_ROTATION_DEG = 30.0
METRIC_KEYS: tuple[str, ...] = ("E_t", "E_r", "E_j", "E_ft", "success")




def compute_metrics(
    object_pose_sim: FloatArray,
    object_pose_ref: FloatArray,
    keypoints_sim: Mapping[str, FloatArray],
    keypoints_ref: Mapping[str, FloatArray],
    valid: Mapping[str, npt.NDArray[np.bool_]],
) -> dict[str, Any]:
    """Metrics of one trajectory. Poses (F,7) world x y z qw qx qy qz; keypoints side -> (F,21,3); valid
    side -> (F,). Returns ``E_t`` (cm), ``E_r`` (deg), ``E_j`` (cm), ``E_ft`` (cm), ``success`` (bool),
    ``max_E_t``, ``max_E_r``, ``frames``, and ``per_frame`` (dict of (F,) arrays ``e_t_cm``, ``e_r_deg``,
    ``e_j_cm``, ``e_ft_cm`` — hand errors NaN on frames where no hand is valid). Use ``scalar_metrics`` for JSON.
    """
    if object_pose_sim.shape != object_pose_ref.shape or object_pose_sim.ndim != 2 or object_pose_sim.shape[1] != 7:
        raise ValueError(
            f"object_pose_sim and object_pose_ref must both be (F, 7), got {object_pose_sim.shape}, "
            f"{object_pose_ref.shape}"
        )
    n = object_pose_sim.shape[0]
    e_t = 100.0 * np.linalg.norm(object_pose_sim[:, :3] - object_pose_ref[:, :3], axis=1)
    e_r = rotation_error_deg(object_pose_sim[:, 3:], object_pose_ref[:, 3:])
    j_sum, j_cnt = np.zeros(n), np.zeros(n)
    ft_sum, ft_cnt = np.zeros(n), np.zeros(n)
    tips = list(FINGERTIP_INDICES)
    for side, sim in keypoints_sim.items():
        ref, ok = keypoints_ref[side], np.asarray(valid[side], dtype=bool)
        if sim.shape != (n, 21, 3) or ref.shape != (n, 21, 3) or ok.shape != (n,):
            raise ValueError(
                f"keypoints_sim[{side!r}], keypoints_ref[{side!r}] must be ({n}, 21, 3) and valid[{side!r}] "
                f"({n},); got {sim.shape}, {ref.shape}, {ok.shape}"
            )
        err = 100.0 * np.linalg.norm(sim - ref, axis=2)  # (F,21) cm
        j_sum += np.where(ok, err.sum(axis=1), 0.0)
        j_cnt += np.where(ok, 21, 0)
        ft_sum += np.where(ok, err[:, tips].sum(axis=1), 0.0)
        ft_cnt += np.where(ok, len(tips), 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        e_j = np.where(j_cnt > 0, j_sum / j_cnt, np.nan)
        e_ft = np.where(ft_cnt > 0, ft_sum / ft_cnt, np.nan)
    has_hand = j_cnt > 0
    return {
        "E_t": float(e_t.mean()),
        "E_r": float(e_r.mean()),
        "E_j": float(j_sum.sum() / j_cnt.sum()) if has_hand.any() else float("nan"),
        "E_ft": float(ft_sum.sum() / ft_cnt.sum()) if has_hand.any() else float("nan"),
        "success": bool(np.all(e_t <= SUCCESS_POSITION_CM) and np.all(e_r <= SUCCESS_ROTATION_DEG)),
        "max_E_t": float(e_t.max()),
        "max_E_r": float(e_r.max()),
        "frames": int(n),
        "per_frame": {"e_t_cm": e_t, "e_r_deg": e_r, "e_j_cm": e_j, "e_ft_cm": e_ft},
    }


def scalar_metrics(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """The JSON-ready part of ``compute_metrics`` output (no per-frame arrays)."""
    return {k: v for k, v in metrics.items() if k != "per_frame"}
