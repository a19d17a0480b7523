"""A robot's joint motion brought within its joint speed limits (issue #55: an executable trajectory).

A recorded human grasp can close faster than a robot's servos turn (DexYCB's grasps close at 3-4x an Allegro's
3.14 rad/s, ``bench/results/robot_hands.md``), so the retargeted motion is not one the real hand can follow.
``speed_limited`` replaces each joint's track by the closest one (least squares over the frames) whose step
between consecutive frames stays within ``fraction`` x the joint's limit / fps: the motion starts earlier and
ends later where it was too fast and is unchanged elsewhere. Each joint is one bounded least-squares problem
(``scipy.optimize.lsq_linear``, BVLS: exact) in the start value and the bounded steps; the joint limits stay met
(clipping a track into them keeps its steps within the bound and brings it closer).

``SPEED_FRACTION`` leaves headroom under the limit for the refinement's offsets and the servos' tracking, which
the ``robot_speed`` loss term (``worker.refine.losses``) charges beyond the limit itself.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear

from common.geometry import FloatArray

#: The retargeted motion is limited to this fraction of each joint's speed limit.
SPEED_FRACTION = 0.9


def speed_limited(q: FloatArray, velocity_limits: FloatArray, fps: float, q_limits: FloatArray | None = None,
                  fraction: float = SPEED_FRACTION) -> FloatArray:
    """``q`` (T, H) with every joint's frame-to-frame step within ``fraction`` x ``velocity_limits`` (H,, rad/s;
    inf or <= 0: no limit) / ``fps``, the closest such track in least squares (module docstring); ``q_limits``
    (H, 2) clip the result. Joints already within their limit are returned unchanged (bit for bit)."""
    q = np.asarray(q, dtype=np.float64)
    out = q.copy()
    t = q.shape[0]
    if t < 2:
        return out
    steps = np.abs(np.diff(q, axis=0)).max(axis=0)
    lower = None
    for j, vmax in enumerate(velocity_limits):
        if not (np.isfinite(vmax) and vmax > 0):
            continue
        bound = fraction * float(vmax) / fps
        if steps[j] <= bound:
            continue
        if lower is None:  # x = A z with z = (x_0, step_1, ..., step_{T-1})
            lower = np.tril(np.ones((t, t)))
        lo = np.r_[-np.inf, np.full(t - 1, -bound)]
        hi = np.r_[np.inf, np.full(t - 1, bound)]
        z = lsq_linear(lower, q[:, j], bounds=(lo, hi), method="bvls").x
        track = np.cumsum(z)
        if q_limits is not None:
            track = np.clip(track, q_limits[j, 0], q_limits[j, 1])
        out[:, j] = track
    return out


def step_ratio(q: FloatArray, velocity_limits: FloatArray, fps: float) -> float | None:
    """The largest frame-to-frame joint speed of ``q`` (T, H) over its limit (None: no limits known)."""
    vmax = np.where(np.isfinite(velocity_limits) & (velocity_limits > 0), velocity_limits, np.nan)
    if len(q) < 2 or not np.isfinite(vmax).any():
        return None
    return float(np.nanmax(np.abs(np.diff(q, axis=0)).max(axis=0) * fps / vmax))
