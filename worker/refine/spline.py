"""Keyframe schedule and cubic interpolation of the control offsets (DESIGN §1.3, issue #3 item 1).

The offsets delta = [10 pose-PCA coefficients, 3 wrist rotation (, 3 wrist translation)] live on keyframes
every K frames and are interpolated with a uniform Catmull-Rom cubic spline. Catmull-Rom is chosen because it
interpolates the keyframes and has local support: the curve on segment [k, k+1] depends only on keyframes
k-1, k, k+1, k+2. That is what makes the sliding window of DESIGN §1.6 exact: once window (k1, k2, k3, k4) has
optimised k3, the segment [k1, k2] depends only on keyframes <= k3, all final, so the state committed at k2
is exactly the state the final from-scratch replay reaches there. Keyframes outside [0, N) count as zero
(no offset), which is the natural padding for offsets.

Interpolation is linear in the keyframe values, so it is a fixed weight matrix: delta(times) = W @ P.
"""

from __future__ import annotations

import numpy as np

from common.geometry import FloatArray


def default_keyframe_interval(fps: float) -> int:
    """K = round(fps / 6): 5 at 30 fps, 10 at 60 fps (about six keyframes per second)."""
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    return max(1, round(fps / 6.0))


def num_keyframes(num_frames: int, interval: int) -> int:
    """Keyframes at frames 0, K, 2K, ... up to the first one at or past the last frame."""
    if num_frames < 1 or interval < 1:
        raise ValueError(f"num_frames and interval must be >= 1, got {num_frames}, {interval}")
    return (num_frames - 1 + interval - 1) // interval + 1


def catmull_rom_weights(times: FloatArray, interval: int, n_keyframes: int) -> FloatArray:
    """(len(times), n_keyframes) weights so that delta(times) = W @ keyframes.

    ``times`` are in frames (fractional for physics substeps). Uniform Catmull-Rom basis on segment
    a = floor(t / K), u = t / K - a:  p(u) = 0.5 * [(-u^3 + 2u^2 - u) P_{a-1} + (3u^3 - 5u^2 + 2) P_a
    + (-3u^3 + 4u^2 + u) P_{a+1} + (u^3 - u^2) P_{a+2}].
    """
    times = np.asarray(times, dtype=np.float64)
    if times.ndim != 1:
        raise ValueError(f"times must be 1-D, got shape {times.shape}")
    s = times / interval
    a = np.floor(s).astype(np.int64)
    u = s - a
    # Clamp the last point exactly onto the last keyframe's segment end.
    last = a >= n_keyframes - 1
    a[last] = n_keyframes - 2 if n_keyframes >= 2 else 0
    u[last] = s[last] - a[last]
    u2, u3 = u * u, u * u * u
    coeffs = 0.5 * np.stack(
        [-u3 + 2 * u2 - u, 3 * u3 - 5 * u2 + 2, -3 * u3 + 4 * u2 + u, u3 - u2], axis=1
    )  # (n, 4) for P_{a-1}, P_a, P_{a+1}, P_{a+2}
    out = np.zeros((len(times), n_keyframes))
    rows = np.arange(len(times))
    for j, offset in enumerate((-1, 0, 1, 2)):
        idx = a + offset
        ok = (idx >= 0) & (idx < n_keyframes)
        np.add.at(out, (rows[ok], idx[ok]), coeffs[ok, j])
    return out


def substep_times(frame_start: int, frame_end: int, substeps: int) -> FloatArray:
    """Fractional frame times of the physics substeps that advance frame_start -> frame_end.

    Substep i of frame f runs from f + i/S to f + (i+1)/S; its control is held from its start.
    """
    if frame_end < frame_start or substeps < 1:
        raise ValueError(f"need frame_end >= frame_start and substeps >= 1, got {frame_start}, {frame_end}, {substeps}")
    n = (frame_end - frame_start) * substeps
    return frame_start + np.arange(n, dtype=np.float64) / substeps


def keyframe_window(j: int, n_keyframes: int, interval: int, num_frames: int, lookahead: int = 1
                    ) -> tuple[int, int]:
    """Frames [start, end] simulated when optimising keyframe j: from keyframe j-2 to keyframe j+lookahead.

    Keyframe j shapes the segments starting at j-2, j-1, j, j+1; the window simulates from the committed
    state at keyframe j-2 up to keyframe j+1 (lookahead 1, the window (k1..k4) of DESIGN §1.6), or further
    so the optimiser sees more of the consequences (the offset is held there, see ``controls.offsets``).
    """
    if not 0 <= j < n_keyframes:
        raise ValueError(f"keyframe index {j} outside [0, {n_keyframes})")
    start = max(0, (j - 2) * interval)
    end = min(num_frames - 1, (j + lookahead) * interval)
    return start, max(end, min(start + 1, num_frames - 1))
