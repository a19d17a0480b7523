"""From keyframe offsets to per-substep hinge targets and wrist poses (DESIGN §1.3, issue #3 item 1).

Per hand, the controls at fractional frame time t are

    q(t)      = clip(q_ref(t) + B10^T (sigma * dtheta(t)), joint limits)   hinge position-servo targets
    R_w(t)    = exp(omega_scale * domega(t)) * R_ref(t)                     wrist orientation (mocap)
    p_w(t)    = c(t) + exp(omega_scale * domega(t)) (p_ref(t) - c(t))
                [+ translation_scale * dp(t)]                               wrist position (mocap)

with delta(t) = [dtheta (10), domega (3)(, dp (3))] the Catmull-Rom interpolation of the keyframes
(``spline``). dtheta is in units of each PCA component's standard deviation ("normalised to unit
variance"), so one CMA-ES step size fits every coordinate. The reference itself is interpolated linearly
(positions, angles) and by slerp (wrist) between frames.

c(t) is the point the rotation offset turns the whole hand about (``pivot``; the wrist itself when none is
given, which is DESIGN §1.3's ``exp(domega) R_ref`` with the translation left as recorded). The refinement
passes the centroid of the reference keypoints (``prepare.ROTATION_PIVOT``), near the centre of the grasp: a
held object then turns about itself when the optimiser turns the hand, instead of swinging on an ~8 cm lever
around the wrist, so correcting the object's rotation no longer moves it, and the keypoints move least. The
wrist leaves its recorded path by at most |domega| * |p_ref - c| (0.3 rad * ~8 cm at the bound).

Left hands (``mirrored``) use the right hand's coordinates reflected through the world yz plane: the
rotation offset is applied as ``MIRROR_ROTATION * domega`` (a rotation vector is a pseudo-vector: reflecting
a rotation through the plane with normal x keeps its x component and negates y and z) and a free translation
as ``MIRROR_TRANSLATION * dp``; ``prepare`` gives them the pose basis with abductions and twists negated
(``worker.hand.model.MIRROR_SIGNS``). Then a sequence and its mirror image through that plane
(``common.sequence_mirror``) are the same optimisation problem, sample for sample: CMA-ES draws the same
coordinates for both and each drives the mirror image of the other's hand. CMA-ES is isotropic, so for
any other left hand the choice of plane changes nothing on average.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import FloatArray, IntArray, quat_exp, quat_mul, quat_rotate, slerp_frames
from worker.refine.spline import catmull_rom_weights, num_keyframes

N_POSE = 10
N_ROT = 3
N_TRANS = 3
#: Radians of wrist rotation per unit of the optimised rotation coordinates.
OMEGA_SCALE = 0.1
#: Metres of wrist translation per unit of the optimised translation coordinates (option).
TRANSLATION_SCALE = 0.02
#: How a mirrored (left) hand's rotation and translation coordinates map to world offsets (module docstring).
MIRROR_ROTATION = np.array([1.0, -1.0, -1.0])
MIRROR_TRANSLATION = np.array([-1.0, 1.0, 1.0])










def lerp_frames(values: FloatArray, times: FloatArray) -> FloatArray:
    """Linear interpolation of a (T, ...) per-frame track at fractional frame ``times``."""
    t_max = values.shape[0] - 1
    times = np.clip(times, 0, t_max)
    i0 = np.minimum(np.floor(times).astype(np.int64), max(t_max - 1, 0))
    i1 = np.minimum(i0 + 1, t_max)
    u = (times - i0).reshape((-1,) + (1,) * (values.ndim - 1))
    return (1 - u) * values[i0] + u * values[i1]


@dataclass
class PoseBasis10:
    """The first 10 PCA components over the 45 hinge angles and their standard deviations."""

    components: FloatArray  # (10, 45)
    stddev: FloatArray  # (10,)

    def __post_init__(self) -> None:
        if self.components.ndim != 2 or self.components.shape[0] != N_POSE:
            raise ValueError(f"components must have shape (10, n_hinges), got {self.components.shape}")
        if self.stddev.shape != (N_POSE,):
            raise ValueError(f"stddev must have shape (10,), got {self.stddev.shape}")


@dataclass
class HandControlSpace:
    """One hand's reference, sampled at every physics substep, and the map offsets -> controls."""

    side: str
    q_ref: FloatArray  # (T, H) hinge angles, H = 45 for the MANO-topology hand
    wrist_pos: FloatArray  # (T, 3)
    wrist_quat: FloatArray  # (T, 4) wxyz
    q_limits: FloatArray  # (H, 2)
    basis: PoseBasis10
    interval: int
    substeps: int
    free_translation: bool = False
    #: (T, 3) world point the rotation offset turns the hand about (None: the wrist, see the module docstring).
    pivot: FloatArray | None = None
    #: Rotation/translation coordinates reflected through the world yz plane (left hands; module docstring).
    mirrored: bool = False

    def __post_init__(self) -> None:
        if self.q_ref.ndim != 2:
            raise ValueError(f"q_ref must have shape (T, n_hinges), got {self.q_ref.shape}")
        t, h = self.q_ref.shape
        for name, arr, shape in (
            ("wrist_pos", self.wrist_pos, (t, 3)),
            ("wrist_quat", self.wrist_quat, (t, 4)),
            ("q_limits", self.q_limits, (h, 2)),
            ("basis.components", self.basis.components, (N_POSE, h)),
            *((("pivot", self.pivot, (t, 3)),) if self.pivot is not None else ()),
        ):
            if arr.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
        self.num_frames = t
        self.n_keyframes = num_keyframes(t, self.interval)
        # Sample times: every substep start, plus the last frame itself.
        n_sub = (t - 1) * self.substeps + 1
        times = np.arange(n_sub, dtype=np.float64) / self.substeps
        self._q_sub = lerp_frames(self.q_ref, times)
        self._p_sub = lerp_frames(self.wrist_pos, times)
        self._r_sub = slerp_frames(self.wrist_quat, times)
        self._c_sub = None if self.pivot is None else lerp_frames(self.pivot, times)
        self._weights = catmull_rom_weights(times, self.interval, self.n_keyframes)
        self._pose_map = self.basis.components.T * self.basis.stddev  # (45, 10): unit coeffs -> radians

    @property
    def dim(self) -> int:
        """Offset coordinates per keyframe: 13, or 16 with a free wrist translation."""
        return N_POSE + N_ROT + (N_TRANS if self.free_translation else 0)

    def zero_keyframes(self) -> FloatArray:
        return np.zeros((self.n_keyframes, self.dim))

    @property
    def last_sample(self) -> int:
        """Index of the last reference sample (the last frame); later substeps hold it."""
        return (self.num_frames - 1) * self.substeps

    def offsets(self, keyframes: FloatArray, idx: IntArray, j: int | None = None,
                candidates: FloatArray | None = None, hold: bool = True) -> FloatArray:
        """Interpolated offsets (C, len(idx), dim) at reference samples ``idx`` (substep times idx / S).

        With ``j`` and ``candidates`` (C, dim), keyframe j *and every later keyframe* take each candidate in
        turn (one CMA-ES population): the offset is held beyond the keyframe being optimised, so the window's
        tail is not pulled back to keyframes that are not optimised yet. ``hold=False`` replaces keyframe j alone
        (the later keyframes are final ones of an earlier pass: ``windowed.optimise_windows``'s polish). Otherwise
        C = 1 with ``keyframes``.
        """
        if keyframes.shape != (self.n_keyframes, self.dim):
            raise ValueError(f"keyframes must have shape {(self.n_keyframes, self.dim)}, got {keyframes.shape}")
        w = self._weights[idx]
        if j is None or candidates is None:
            return (w @ keyframes)[None]
        if candidates.ndim != 2 or candidates.shape[1] != self.dim:
            raise ValueError(f"candidates must have shape (C, {self.dim}), got {candidates.shape}")
        if not hold:
            others = w @ keyframes - np.outer(w[:, j], keyframes[j])  # (n, dim): every keyframe but j
            return others[None] + w[None, :, j, None] * candidates[:, None, :]
        base = w[:, :j] @ keyframes[:j]  # (n, dim)
        tail = w[:, j:].sum(axis=1)
        return base[None] + tail[None, :, None] * candidates[:, None, :]

    def controls(self, offsets: FloatArray, idx: IntArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Hinge targets (C, n, H), wrist positions (C, n, 3), wrist quaternions (C, n, 4) at reference
        samples ``idx`` (n,) for offsets (C, n, dim) from ``offsets``."""
        q = self._q_sub[idx][None] + offsets[..., :N_POSE] @ self._pose_map.T
        q = np.clip(q, self.q_limits[:, 0], self.q_limits[:, 1])
        omega = offsets[..., N_POSE : N_POSE + N_ROT]
        rot = quat_exp(OMEGA_SCALE * (omega * MIRROR_ROTATION if self.mirrored else omega))
        quat = quat_mul(rot, np.broadcast_to(self._r_sub[idx][None], rot.shape))
        pos = np.broadcast_to(self._p_sub[idx][None], (offsets.shape[0], len(idx), 3)).copy()
        if self._c_sub is not None:
            # Added as a difference so a zero offset leaves the recorded path bit-identical (raw replay).
            arm = pos - self._c_sub[idx][None]
            pos += quat_rotate(rot, arm) - arm
        if self.free_translation:
            dp = offsets[..., N_POSE + N_ROT :]
            pos += TRANSLATION_SCALE * (dp * MIRROR_TRANSLATION if self.mirrored else dp)
        return q, pos, quat

    def frame_joint_targets(self, offsets: FloatArray, frames: IntArray) -> FloatArray:
        """Hinge targets (C, n, H) at frames (n,) for offsets (C, n, dim) there: ``controls``' first part alone."""
        q = self._q_sub[frames * self.substeps][None] + offsets[..., :N_POSE] @ self._pose_map.T
        return np.clip(q, self.q_limits[:, 0], self.q_limits[:, 1])

    def frame_controls(self, keyframes: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Per-frame hinge targets (T, H), wrist positions (T, 3), quaternions (T, 4) for the result."""
        idx = np.arange(self.num_frames) * self.substeps
        q, p, r = self.controls(self.offsets(keyframes, idx), idx)
        return q[0], p[0], r[0]
