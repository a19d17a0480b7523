"""Whether a robot hand's trajectory is one a real hand can execute (issue #55 item 3).

From a replay's per-frame joint positions (F, H) and the peak actuator force of each frame's physics steps (F, H):

* ``limit_margin_deg``: the closest any actuated joint comes to a limit (degrees or, for a slide, millimetres
  read as degrees' worth: hands are hinges), and ``at_limit_share`` the share of frames with a joint within
  ``AT_LIMIT_DEG`` of one;
* ``force_peak_ratio``: the largest |actuator force| / the joint's effort limit (the servos are force-limited at
  it, so 1 means saturated), and ``force_saturated_share`` the share of frames in which a servo is saturated
  (within 1 %); None without effort limits;
* ``peak_velocity`` (rad/s) and ``velocity_ratio`` = the largest |dq/dt| / the joint's speed limit (URDF ``limit
  velocity`` or the description's; None without), by central differences at the frame rate, for the simulated
  joints and for the commanded servo targets (``command_velocity_ratio``): above 1 the motion is too fast to send;
* ``speed_limit_exceeded``: whether either ratio is above 1 (None without limits), and ``speed_limit_frame`` the
  frame of the larger one's peak (None within the limits): the outcome says so (``robot_too_fast``);
* ``peak_acceleration`` (rad/s²): the largest |d²q/dt²| of the simulated joints (the models give no limit).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from common.geometry import FloatArray

AT_LIMIT_DEG = 1.0
SATURATED = 0.99


def robot_motion_metrics(q_sim: FloatArray, q_command: FloatArray, force_peak: FloatArray, limits: FloatArray,
                         velocity_limits: FloatArray, effort_limits: FloatArray, fps: float) -> dict[str, Any]:
    """See the module docstring. ``q_sim`` / ``q_command`` / ``force_peak`` (F, H); ``limits`` (H, 2)."""
    margin = np.minimum(q_sim - limits[:, 0], limits[:, 1] - q_sim)  # (F, H)
    out: dict[str, Any] = {
        "limit_margin_deg": float(np.degrees(margin.min())),
        "at_limit_share": float((np.degrees(margin) <= AT_LIMIT_DEG).any(axis=1).mean()),
    }
    effort = np.where(np.isfinite(effort_limits) & (effort_limits > 0), effort_limits, np.nan)
    if np.isfinite(effort).any():
        ratio = np.abs(force_peak) / effort
        out["force_peak_ratio"] = float(np.nanmax(ratio))
        out["force_saturated_share"] = float((np.nan_to_num(ratio) >= SATURATED).any(axis=1).mean())
    else:
        out["force_peak_ratio"] = out["force_saturated_share"] = None
    dt = 1.0 / fps
    vel = np.gradient(q_sim, dt, axis=0) if len(q_sim) > 1 else np.zeros_like(q_sim)
    cmd_vel = np.gradient(q_command, dt, axis=0) if len(q_command) > 1 else np.zeros_like(q_command)
    acc = np.gradient(vel, dt, axis=0) if len(q_sim) > 1 else np.zeros_like(q_sim)
    out["peak_velocity"] = float(np.abs(vel).max())
    out["peak_acceleration"] = float(np.abs(acc).max())
    vmax = np.where(np.isfinite(velocity_limits) & (velocity_limits > 0), velocity_limits, np.nan)
    has_v = bool(np.isfinite(vmax).any())
    out["velocity_ratio"] = out["command_velocity_ratio"] = out["speed_limit_exceeded"] = None
    out["speed_limit_frame"] = None
    if has_v:
        ratios = [np.nan_to_num(np.abs(v) / vmax) for v in (vel, cmd_vel)]  # (F, H) each
        out["velocity_ratio"], out["command_velocity_ratio"] = (float(r.max()) for r in ratios)
        peak = max(ratios, key=lambda r: float(r.max()))
        out["speed_limit_exceeded"] = bool(peak.max() > 1.0)
        if out["speed_limit_exceeded"]:
            out["speed_limit_frame"] = int(np.unravel_index(int(np.argmax(peak)), peak.shape)[0])
    return out
