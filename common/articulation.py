"""Articulated objects: rigid parts joined by revolute and prismatic joints (issue #52 item 1).

An articulated object is its *base* part (the ``ObjectSpec``'s own mesh or primitive, posed by the sequence's
``object_pose``) plus further parts (``ObjectSpec.parts``), each hung from the base or from an earlier part by one
joint, so the parts form a tree. The conventions are URDF's and MJCF's:

* a part's frame, at joint value 0, is its parent's frame moved by ``origin_pos`` / ``origin_quat`` (the child
  frame in the parent frame);
* the joint acts in the part's own frame, about (revolute, radians) or along (prismatic, metres) the unit
  ``axis`` through the part frame's origin: ``T_parent_part(a) = T_origin * Rot(axis, a)`` or ``* Trans(axis a)``;
* the recorded value of every joint per frame is ``Sequence.articulation`` (T, J), within ``limits``.

This module holds the joint description, forward kinematics (part poses from the base pose and the values) and
the field-named checks ``Sequence.validate`` runs. NumPy only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from common.errors import FieldProblem
from common.geometry import FloatArray, quat_exp, quat_mul, quat_rotate
from common.safe_text import shown, text_problem

JointKind = Literal["revolute", "prismatic"]
JOINT_KINDS: tuple[str, ...] = ("revolute", "prismatic")
#: The base part's name when the file gives none (contacts and results name parts by these names).
DEFAULT_BASE_PART = "base"
#: Most parts beyond the base: ARCTIC's objects have one joint; a drawer cabinet a handful.
MAX_PARTS = 16
#: A recorded value this far outside its joint's limits (radians or metres) still counts as within them: the
#: float32 storage of real recordings rounds values sitting on a limit to either side of it.
LIMIT_TOLERANCE = 1e-4
#: A joint's travel may not exceed this (radians for revolute; prismatic travel is bounded by the 5 m extent).
MAX_REVOLUTE_RANGE = 4 * np.pi
MAX_PRISMATIC_RANGE = 5.0


@dataclass
class ObjectJoint:
    """The joint that hangs one part from its parent (module docstring for the conventions)."""

    name: str
    kind: JointKind
    parent: str  # the base part's name or an earlier part's
    axis: FloatArray  # (3,) unit vector in the part's frame
    origin_pos: FloatArray  # (3,) the part frame's origin in the parent frame at value 0
    origin_quat: FloatArray  # (4,) wxyz, the part frame's orientation in the parent frame at value 0
    limits: FloatArray  # (2,) lower, upper (radians or metres)
    #: Joint damping (N m s / rad or N s / m) and dry friction (N m or N); None: ``SimConfig``'s defaults.
    damping: float | None = None
    friction: float | None = None

    @property
    def unit(self) -> str:
        """The unit errors of this joint are reported in (degrees or centimetres)."""
        return "deg" if self.kind == "revolute" else "cm"

    def display_scale(self) -> float:
        """Factor from the joint's SI value (rad or m) to its reported unit (deg or cm)."""
        return float(np.degrees(1.0)) if self.kind == "revolute" else 100.0


def joint_transform(joint: ObjectJoint, values: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(T, 3) positions and (T, 4) quaternions of the part frame in the parent frame at joint ``values`` (T,)."""
    values = np.asarray(values, dtype=np.float64)
    axis = np.asarray(joint.axis, dtype=np.float64)
    origin_q = np.broadcast_to(np.asarray(joint.origin_quat, dtype=np.float64), (*values.shape, 4))
    origin_p = np.broadcast_to(np.asarray(joint.origin_pos, dtype=np.float64), (*values.shape, 3))
    if joint.kind == "revolute":
        motion = quat_exp(values[..., None] * axis)
        return origin_p.copy(), quat_mul(origin_q, motion)
    return origin_p + quat_rotate(origin_q, values[..., None] * axis), origin_q.copy()


def part_poses(base_pose: FloatArray, joints: list[ObjectJoint], parents: list[int], values: FloatArray) -> FloatArray:
    """(..., 1 + J, 7) world poses of every part (base first, then the parts in ``joints`` order) from base poses
    (..., 7) and joint values (..., J); ``parents[k]`` is part k's parent as an index into that output (0: the
    base), always smaller than k + 1 (``validate_articulation`` keeps parents before children)."""
    base_pose = np.asarray(base_pose, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    out = np.empty((*base_pose.shape[:-1], 1 + len(joints), 7))
    out[..., 0, :] = base_pose
    for k, joint in enumerate(joints):
        parent = out[..., parents[k], :]
        rel_p, rel_q = joint_transform(joint, values[..., k])
        out[..., k + 1, :3] = parent[..., :3] + quat_rotate(parent[..., 3:], rel_p)
        out[..., k + 1, 3:] = quat_mul(parent[..., 3:], rel_q)
    return out


def validate_joints(
    problems: list[FieldProblem], joints: list[ObjectJoint], names: list[str], articulation: object, t: int | None,
    prefix: str = "object.parts",
) -> None:
    """Field-named checks of the joints (``joints[k]`` hangs part ``names[k + 1]``; ``names[0]`` is the base) and
    of the recorded values (T, J). Normalises each axis and origin quaternion once they pass."""
    add = lambda f, p: problems.append(FieldProblem(f, p))  # noqa: E731
    if len(joints) > MAX_PARTS:
        add(prefix, f"at most {MAX_PARTS} parts beyond the base, got {len(joints)}")
        return
    seen: set[str] = set()
    for name in names:
        if name in seen:
            add(prefix, f"part names must be unique, {shown(name)} appears twice")
        seen.add(name)
    ok = True
    for k, joint in enumerate(joints):
        f = f"{prefix}[{k}].joint"
        if (why := text_problem(joint.name, 200)) is not None or not joint.name:
            add(f"{f}.name", why or "must not be empty")
        if joint.kind not in JOINT_KINDS:
            add(f"{f}.type", f"must be one of {', '.join(JOINT_KINDS)}, got {shown(joint.kind)}")
            ok = False
        if joint.parent not in names[: k + 1]:
            where = "the base part or an earlier part" if joint.parent not in names else "a part listed before it"
            add(f"{f}.parent", f"must name {where} (parts form a tree), got {shown(joint.parent)}")
            ok = False
        ok &= _vector(problems, f"{f}.axis", joint.axis, 3, nonzero=True)
        ok &= _vector(problems, f"{f}.origin.pos", joint.origin_pos, 3)
        if _vector(problems, f"{f}.origin.quat", joint.origin_quat, 4, nonzero=True):
            norm = float(np.linalg.norm(joint.origin_quat))
            if abs(norm - 1.0) > 1e-3:
                add(f"{f}.origin.quat", f"must be a unit quaternion (w x y z), norm is {norm:.4f}")
                ok = False
        else:
            ok = False
        if _vector(problems, f"{f}.limits", joint.limits, 2):
            lo, hi = (float(v) for v in joint.limits)
            bound = MAX_REVOLUTE_RANGE if joint.kind == "revolute" else MAX_PRISMATIC_RANGE
            if lo > hi:
                add(f"{f}.limits", f"lower must not exceed upper, got [{lo:g}, {hi:g}]")
                ok = False
            elif hi - lo > bound:
                add(f"{f}.limits", f"span {hi - lo:g} exceeds {bound:g} ({'rad' if joint.kind == 'revolute' else 'm'})")
                ok = False
        else:
            ok = False
        for key in ("damping", "friction"):
            value = getattr(joint, key)
            if value is not None and not (_is_number(value) and 0 <= float(value) <= 1e3):
                add(f"{f}.{key}", f"must be a number in [0, 1000] when given, got {shown(value)}")
    values = _values(problems, articulation, t, len(joints))
    if not ok or values is None:
        return
    for k, joint in enumerate(joints):
        joint.axis = np.asarray(joint.axis, dtype=np.float64) / np.linalg.norm(joint.axis)
        joint.origin_quat = np.asarray(joint.origin_quat, dtype=np.float64) / np.linalg.norm(joint.origin_quat)
        lo, hi = float(joint.limits[0]), float(joint.limits[1])
        column = values[:, k]
        bad = np.flatnonzero((column < lo - LIMIT_TOLERANCE) | (column > hi + LIMIT_TOLERANCE))
        if bad.size:
            i = int(bad[0])
            add("articulation", f"joint {shown(joint.name)} (column {k}) is {column[i]:.6g} at frame {i}, outside its "
                f"limits [{lo:g}, {hi:g}] ({bad.size} frames in all)")


def _values(problems: list[FieldProblem], articulation: object, t: int | None, n: int) -> FloatArray | None:
    """The recorded joint values (T, J) when they are present and well-formed (problems added otherwise)."""
    if n == 0:
        if articulation is not None:
            problems.append(FieldProblem("articulation", "is given but the object has no jointed parts"))
        return None
    if articulation is None:
        problems.append(FieldProblem("articulation", f"is required for an object with {n} jointed part(s): (T, {n})"))
        return None
    if not isinstance(articulation, np.ndarray) or articulation.ndim != 2 or articulation.shape[1] != n:
        shape = getattr(articulation, "shape", type(articulation).__name__)
        problems.append(FieldProblem("articulation", f"must have shape (T, {n}), got {shape}"))
        return None
    if articulation.dtype.kind not in "biuf" or not np.all(np.isfinite(articulation)):
        problems.append(FieldProblem("articulation", "must hold finite numbers"))
        return None
    if t is not None and articulation.shape[0] != t:
        problems.append(FieldProblem("articulation", f"has {articulation.shape[0]} frames but object_pose has {t}"))
        return None
    return np.asarray(articulation, dtype=np.float64)


def _vector(problems: list[FieldProblem], field: str, value: object, n: int, nonzero: bool = False) -> bool:
    if not isinstance(value, np.ndarray) or value.shape != (n,) or value.dtype.kind not in "iuf":
        problems.append(FieldProblem(field, f"must be {n} numbers, got {shown(getattr(value, 'shape', value))}"))
        return False
    if not np.all(np.isfinite(value)) or np.max(np.abs(value)) > 1e6:
        problems.append(FieldProblem(field, "must hold finite numbers within +-1e6"))
        return False
    if nonzero and float(np.linalg.norm(value)) < 1e-9:
        problems.append(FieldProblem(field, "must not have zero length"))
        return False
    return True


def _is_number(x: object) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and bool(np.isfinite(x))
