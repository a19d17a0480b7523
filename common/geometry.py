"""Rotations and array types shared by every module: wxyz quaternions (scalar first, as MuJoCo stores them),
their products, rotations of vectors, conversions to and from matrices and rotation vectors, spherical
interpolation, and the angle between two rotations.

One module, so that a formula (and its rounding) exists once; NumPy only, broadcasting over leading axes.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: Below this sin(angle) two quaternions count as equal in ``slerp``: the weights fall back to linear ones,
#: which agree with the spherical weights to far below float64 resolution there.
SLERP_LINEAR_BELOW = 1e-8


def quat_mul(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product of wxyz quaternions, broadcasting over leading dimensions."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """``np.cross`` of (..., 3) vectors, broadcasting: the same products and differences, so the same bits, without
    its axis bookkeeping, which costs more than the arithmetic on the small arrays of the hand's IK."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def quat_conj(q: FloatArray) -> FloatArray:
    """Conjugate (the inverse of a unit quaternion)."""
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_rotate(q: FloatArray, v: FloatArray) -> FloatArray:
    """Rotate vectors v (..., 3) by unit wxyz quaternions q (..., 4): v + 2w (u x v) + 2 u x (u x v)."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return np.asarray(v + w * t + np.cross(u, t))


def quat_exp(rotvec: FloatArray) -> FloatArray:
    """wxyz quaternion of a rotation vector (axis * angle), broadcasting over leading dimensions."""
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(x/2)/x -> 1/2 as x -> 0; the series keeps small angles exact.
    small = angle < 1e-8
    scale = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), rotvec * scale], axis=-1)


def quat_to_matrix(quat: FloatArray) -> FloatArray:
    """(...,4) wxyz quaternions -> (...,3,3) rotation matrices."""
    q = np.asarray(quat, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(rot: FloatArray) -> FloatArray:
    """3x3 rotation -> wxyz quaternion (w >= 0)."""
    q = Rotation.from_matrix(rot).as_quat(scalar_first=True)
    return q if q[0] >= 0 else -q


def slerp(q0: FloatArray, q1: FloatArray, t: FloatArray) -> FloatArray:
    """Spherical interpolation of wxyz quaternions (...,4) at fractions t (...); shortest path."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[..., None] < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    small = sin < SLERP_LINEAR_BELOW
    w0 = np.where(small, 1 - t, np.sin((1 - t) * theta) / np.where(small, 1.0, sin))
    w1 = np.where(small, t, np.sin(t * theta) / np.where(small, 1.0, sin))
    out = w0[..., None] * q0 + w1[..., None] * q1
    return np.asarray(out / np.linalg.norm(out, axis=-1, keepdims=True))


def slerp_frames(quats: FloatArray, times: FloatArray) -> FloatArray:
    """Slerp a (T, 4) per-frame quaternion track at fractional frame ``times``."""
    t_max = quats.shape[0] - 1
    times = np.clip(times, 0, t_max)
    i0 = np.minimum(np.floor(times).astype(np.int64), max(t_max - 1, 0))
    i1 = np.minimum(i0 + 1, t_max)
    return slerp(quats[i0], quats[i1], times - i0)


def rotation_angle(quat_a: FloatArray, quat_b: FloatArray) -> FloatArray:
    """Geodesic angle (rad) between wxyz quaternions (...,4): 2·acos|<a, b>| of the normalised quaternions."""
    a = quat_a / np.linalg.norm(quat_a, axis=-1, keepdims=True)
    b = quat_b / np.linalg.norm(quat_b, axis=-1, keepdims=True)
    dot = np.clip(np.abs(np.sum(a * b, axis=-1)), 0.0, 1.0)
    return np.asarray(2.0 * np.arccos(dot))


def rotation_error_deg(quat_a: FloatArray, quat_b: FloatArray) -> FloatArray:
    """Geodesic angle (deg) between wxyz quaternions (...,4)."""
    return np.asarray(np.degrees(rotation_angle(quat_a, quat_b)))


def quat_axis_angle(quat: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit rotation axis (..., 3) and angle (...,) in radians of wxyz quaternions (..., 4), the short way (q and
    -q are one rotation). The arctan2 form stays accurate near 0 where ``rotation_angle``'s arccos does not; the
    axis of a zero rotation is zero."""
    q = np.where(quat[..., :1] < 0, -quat, quat)
    sin_half = np.linalg.norm(q[..., 1:], axis=-1)
    angle = 2 * np.arctan2(sin_half, q[..., 0])
    axis = q[..., 1:] / np.maximum(sin_half, 1e-12)[..., None]
    return np.asarray(axis), np.asarray(angle)
