"""The in-memory sequence: one object (rigid, or articulated: ``common.articulation``), one or two hands, per-frame
poses, and the world frame.

A ``Sequence`` is self-contained (the object mesh is held as vertices + faces, never as a path) so it can
travel through the queue and be re-run anywhere. Arrays are NumPy; every constructor path goes through
``validate()``, which collects *every* problem and raises one ``SequenceValidationError`` naming the fields.

Frames: poses are given in a source frame (usually a camera); ``world_from_source`` maps them to the
gravity-aligned world (table plane z = 0, +z up, DESIGN §1). When only an up vector is known, the world
origin is put under the frame-0 object and the table at the object's lowest frame-0 point.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import numpy.typing as npt

from common.articulation import DEFAULT_BASE_PART, ObjectJoint, part_poses, validate_joints
from common.errors import FieldProblem, SequenceValidationError
from common.geometry import FloatArray, IntArray
from common.safe_text import meta_problems, shown, text_problem

BoolArray = npt.NDArray[np.bool_]

Side = Literal["right", "left"]
PrimitiveKind = Literal["box", "cylinder", "sphere", "capsule"]

#: MANO21 / OpenPose joint order: wrist, then thumb, index, middle, ring, pinky (base to tip).
JOINT_NAMES: tuple[str, ...] = (
    "wrist",
    "thumb1", "thumb2", "thumb3", "thumb4",
    "index1", "index2", "index3", "index4",
    "middle1", "middle2", "middle3", "middle4",
    "ring1", "ring2", "ring3", "ring4",
    "pinky1", "pinky2", "pinky3", "pinky4",
)  # fmt: skip
FINGERTIP_INDICES: tuple[int, ...] = (4, 8, 12, 16, 20)
NUM_JOINTS = 21

#: Number of size values per primitive: box half-extents (x, y, z); cylinder/capsule (radius, half-length
#: along z); sphere (radius).
PRIMITIVE_SIZE_LEN: dict[str, int] = {"box": 3, "cylinder": 2, "capsule": 2, "sphere": 1}

QUATERNION_NORM_TOLERANCE = 1e-3
#: A quaternion whose norm is within this of 1 counts as normalised (a float64 normalisation leaves <= ~3e-16).
UNIT_NORM_ULPS = 1e-15
#: Shortest sequence: a motion, the velocity losses and one simulated step need two frames (issue #16).
MIN_FRAMES = 2
#: Bounds that keep every later computation finite (a coordinate of 1e300 m squares to inf).
MAX_ABS_VALUE = 1e6
MAX_FPS = 1000.0
MAX_MASS_KG = 1000.0
MAX_FRAME_START = 2**31 - 1
MAX_NAME_CHARS = 200


@dataclass
class ObjectSpec:
    """The manipulated object: a primitive or a triangle mesh (object frame), with its mass. An articulated object
    is this shape as its base part (named ``base_part``) plus ``parts`` hung from it by joints."""

    name: str
    mass_kg: float
    primitive: PrimitiveKind | None = None
    size: FloatArray | None = None
    mesh_vertices: FloatArray | None = None
    mesh_faces: IntArray | None = None
    friction: float | None = None
    parts: list[ObjectPart] = field(default_factory=list)
    base_part: str = DEFAULT_BASE_PART

    @property
    def is_mesh(self) -> bool:
        return self.mesh_vertices is not None

    @property
    def articulated(self) -> bool:
        return bool(self.parts)

    @property
    def joints(self) -> list[ObjectJoint]:
        return [p.joint for p in self.parts]

    @property
    def part_names(self) -> list[str]:
        """The base part's name, then every further part's (the order of ``part_poses``)."""
        return [self.base_part] + [p.shape.name for p in self.parts]

    def parent_indices(self) -> list[int]:
        """Each further part's parent as an index into ``part_names`` (0: the base)."""
        index = {name: i for i, name in enumerate(self.part_names)}
        return [index[p.joint.parent] for p in self.parts]

    def part_shapes(self) -> list[ObjectSpec]:
        """Every part's shape, base first (the base is this object without its parts)."""
        return [replace(self, parts=[])] + [p.shape for p in self.parts]

    def part_poses(self, base_pose: FloatArray, values: FloatArray | None) -> FloatArray:
        """(..., P, 7) world poses of the parts (base first) for base poses (..., 7) and joint values (..., J)."""
        if not self.parts:
            return np.asarray(base_pose, dtype=np.float64)[..., None, :].copy()
        assert values is not None
        return part_poses(base_pose, self.joints, self.parent_indices(), values)

    def surface_vertices(self) -> FloatArray:
        """Vertices of the object's surface in the object frame (primitives are tessellated)."""
        if self.mesh_vertices is not None:
            return self.mesh_vertices
        import trimesh  # local: trimesh is only needed for primitives here

        assert self.size is not None and self.primitive is not None
        s = self.size
        if self.primitive == "box":
            mesh = trimesh.creation.box(extents=2 * s)
        elif self.primitive == "sphere":
            mesh = trimesh.creation.icosphere(subdivisions=2, radius=s[0])
        elif self.primitive == "cylinder":
            mesh = trimesh.creation.cylinder(radius=s[0], height=2 * s[1], sections=32)
        else:
            mesh = trimesh.creation.capsule(radius=s[0], height=2 * s[1], count=[16, 16])
        return np.asarray(mesh.vertices, dtype=np.float64)


@dataclass
class ObjectPart:
    """A part of an articulated object beyond its base: its shape and mass, and the joint to its parent."""

    shape: ObjectSpec  # name, mass_kg and a mesh or primitive (its own ``parts`` stay empty)
    joint: ObjectJoint


@dataclass
class ManoParams:
    """MANO parameters per frame, in the source frame (decoded by the MANO module, issue #6)."""

    global_orient: FloatArray  # (T, 3) axis-angle
    hand_pose: FloatArray  # (T, 45) axis-angle or (T, n) PCA coefficients
    trans: FloatArray  # (T, 3)
    betas: FloatArray  # (10,)
    pose_format: Literal["axis_angle", "pca"] = "axis_angle"
    flat_hand_mean: bool = False


@dataclass
class HandTrack:
    """One hand: which side, and keypoints and/or MANO parameters per frame, with a validity mask."""

    side: Side
    valid: BoolArray  # (T,)
    keypoints: FloatArray | None = None  # (T, 21, 3), source frame, metres
    mano: ManoParams | None = None


@dataclass
class Sequence:
    """A hand-object demonstration. Arrays are in the source frame; see ``world_transform()``."""

    name: str
    fps: float
    object: ObjectSpec
    object_pose: FloatArray  # (T, 7): x, y, z, qw, qx, qy, qz
    hands: list[HandTrack]
    frame_start: int = 0
    world_from_source: FloatArray | None = None  # (4, 4)
    up: FloatArray | None = None  # (3,), used when world_from_source is absent
    meta: dict[str, str] = field(default_factory=dict)
    #: (T, J) recorded joint values of an articulated object (radians / metres), None for a rigid one.
    articulation: FloatArray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.object_pose.shape[0])

    @property
    def frame_range(self) -> tuple[int, int]:
        return self.frame_start, self.frame_start + self.num_frames

    def hand(self, side: Side) -> HandTrack | None:
        return next((h for h in self.hands if h.side == side), None)

    # ------------------------------------------------------------------ world frame
    def world_transform(self) -> FloatArray:
        """4x4 rigid transform source -> world (table z = 0, +z up)."""
        if self.world_from_source is not None:
            return self.world_from_source
        rot = np.eye(3)
        if self.up is not None:
            rot = _rotation_taking(self.up / np.linalg.norm(self.up), np.array([0.0, 0.0, 1.0]))
        # Origin under the frame-0 object; table at its lowest frame-0 point (resting start).
        verts0 = _transform_points(self._frame0_vertices(), self.object_pose[0])
        world_verts0 = verts0 @ rot.T
        origin = rot @ self.object_pose[0, :3]
        out = np.eye(4)
        out[:3, :3] = rot
        out[:3, 3] = [-origin[0], -origin[1], -world_verts0[:, 2].min()]
        return out

    def _frame0_vertices(self) -> FloatArray:
        """The object's surface vertices in its base frame, every part posed at its frame-0 joint values."""
        obj = self.object
        if not obj.parts or self.articulation is None:
            return obj.surface_vertices()
        poses = obj.part_poses(np.array([0.0, 0, 0, 1, 0, 0, 0]), self.articulation[0])
        return np.concatenate([_transform_points(shape.surface_vertices(), poses[k])
                               for k, shape in enumerate(obj.part_shapes())])  # fmt: skip

    def object_pose_world(self) -> FloatArray:
        """(T, 7) object poses in the world frame, quaternions scalar first and sign-continuous."""
        return transform_poses(self.world_transform(), self.object_pose)

    def keypoints_world(self, hand: HandTrack) -> FloatArray:
        """(T, 21, 3) keypoints in the world frame (invalid frames keep whatever they held)."""
        if hand.keypoints is None:
            raise SequenceValidationError.single(
                f"hands[{self.hands.index(hand)}].keypoints",
                "this hand has no keypoints (MANO parameters must be decoded first)",
            )
        w = self.world_transform()
        return hand.keypoints @ w[:3, :3].T + w[:3, 3]

    # ------------------------------------------------------------------ validation
    def validate(self, max_frames: int | None = None) -> Sequence:
        """Check everything; raise one ``SequenceValidationError`` listing every problem. Returns self."""
        problems: list[FieldProblem] = []
        add = lambda f, p: problems.append(FieldProblem(f, p))  # noqa: E731

        if (why := text_problem(self.name, MAX_NAME_CHARS)) is not None:
            add("name", why)
        elif not self.name:
            add("name", "must not be empty")
        problems += meta_problems(self.meta)
        if not _is_real(self.fps) or not 0 < self.fps <= MAX_FPS:
            add("fps", f"must be a number in (0, {MAX_FPS:g}], got {shown(self.fps)}")
        if not isinstance(self.frame_start, int) or not 0 <= self.frame_start <= MAX_FRAME_START:
            add("frame_start", f"must be an integer in [0, {MAX_FRAME_START}], got {shown(self.frame_start)}")

        t = _check_array(problems, "object_pose", self.object_pose, (None, 7))
        if t is not None:
            if t < MIN_FRAMES:
                add("object_pose", f"has {t} frame(s); a sequence needs at least {MIN_FRAMES}")
            elif max_frames is not None and t > max_frames:
                add("object_pose", f"has {t} frames, more than the limit of {max_frames}")
            else:
                norms = np.linalg.norm(self.object_pose[:, 3:], axis=1)
                bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE)
                if bad.size:
                    add(
                        "object_pose",
                        f"quaternion (columns 3-6) is not unit length at frame {int(bad[0])} "
                        f"(norm {norms[bad[0]]:.4f}; {bad.size} frames in all)",
                    )
        _validate_object(problems, self.object)
        _validate_parts(problems, self.object, self.articulation, t)

        if not self.hands:
            add("hands", "at least one hand is required")
        if len(self.hands) > 2:
            add("hands", f"at most two hands, got {len(self.hands)}")
        sides = [h.side for h in self.hands]
        if len(set(sides)) != len(sides):
            add("hands", f"each side may appear once, got {sides}")
        for i, hand in enumerate(self.hands):
            _validate_hand(problems, f"hands[{i}]", hand, t)

        if self.world_from_source is not None:
            if _check_array(problems, "world_from_camera", self.world_from_source, (4, 4)) is not None:
                _validate_rigid(problems, "world_from_camera", self.world_from_source)
        elif (
            self.up is not None
            and _check_array(problems, "up", self.up, (3,)) is not None
            and np.linalg.norm(self.up) < 1e-9
        ):
            add("up", "must be a non-zero vector")

        if problems:
            raise SequenceValidationError(problems)
        # Normalise quaternions once validated (float32 sources carry ~1e-7 norm error). Rows already unit to
        # within a few ulp are left alone, so normalising is idempotent: a sequence saved and loaded again is
        # bit-identical. (Dividing a normalised quaternion by its norm again moves it by ~1e-16, and a contact-
        # rich replay turns that into millimetres: results failed ``verify`` because the embedded copy of the
        # input had been normalised once more than the one that was refined; issue #15.)
        self.object_pose = self.object_pose.copy()
        norms = np.linalg.norm(self.object_pose[:, 3:], axis=1)
        off = np.abs(norms - 1.0) > UNIT_NORM_ULPS
        self.object_pose[off, 3:] /= norms[off, None]
        return self


# ---------------------------------------------------------------------- helpers


def _check_array(
    problems: list[FieldProblem], name: str, arr: object, shape: tuple[int | None, ...]
) -> int | None:
    """Check type, shape and finiteness; return the first dimension when all is well."""
    if not isinstance(arr, np.ndarray):
        problems.append(FieldProblem(name, f"must be an array, got {type(arr).__name__}"))
        return None
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape, strict=False)):
        want = "(" + ", ".join("T" if s is None else str(s) for s in shape) + ")"
        problems.append(FieldProblem(name, f"must have shape {want}, got {tuple(arr.shape)}"))
        return None
    if arr.dtype.kind not in "biuf":
        problems.append(FieldProblem(name, f"must hold numbers, got dtype {arr.dtype.str}"))
        return None
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        problems.append(FieldProblem(name, f"contains NaN or Inf (first at index {tuple(int(b) for b in bad)})"))
        return None
    if arr.dtype.kind == "f" and arr.size and np.max(np.abs(arr)) > MAX_ABS_VALUE:
        problems.append(FieldProblem(name, f"holds a value beyond +-{MAX_ABS_VALUE:g}"))
        return None
    return int(arr.shape[0]) if arr.ndim else 0


def _validate_object(problems: list[FieldProblem], obj: ObjectSpec, f: str = "object") -> None:
    """The shape and mass of the object (or of one part, ``f`` naming it)."""
    add = lambda name, p: problems.append(FieldProblem(name, p))  # noqa: E731
    if (why := text_problem(obj.name, MAX_NAME_CHARS)) is not None:
        add(f"{f}.name", why)
    if not _is_real(obj.mass_kg) or not 0 < obj.mass_kg <= MAX_MASS_KG:
        add(f"{f}.mass_kg", f"must be a number of kilograms in (0, {MAX_MASS_KG:g}], got {shown(obj.mass_kg)}")
    if obj.friction is not None and (not _is_real(obj.friction) or not 0 < obj.friction <= 10):
        add(f"{f}.friction", f"must be in (0, 10] when given, got {shown(obj.friction)}")
    has_mesh = obj.mesh_vertices is not None or obj.mesh_faces is not None
    if has_mesh == (obj.primitive is not None):
        add(f, "give exactly one of a mesh (vertices + faces) or a primitive with sizes")
        return
    if obj.primitive is not None:
        if obj.primitive not in PRIMITIVE_SIZE_LEN:
            add(f"{f}.primitive", f"must be one of {sorted(PRIMITIVE_SIZE_LEN)}, got {shown(obj.primitive)}")
            return
        n = PRIMITIVE_SIZE_LEN[obj.primitive]
        if _check_array(problems, f"{f}.size", obj.size, (n,)) is not None:
            assert obj.size is not None
            if np.any(obj.size <= 0) or np.any(obj.size > 5.0):
                add(f"{f}.size", f"sizes must be in (0, 5] metres, got {obj.size.tolist()}")
        return
    nv = _check_array(problems, f"{f}.mesh.vertices", obj.mesh_vertices, (None, 3))
    nf = _check_array(problems, f"{f}.mesh.faces", obj.mesh_faces, (None, 3))
    if nv is None or nf is None:
        return
    assert obj.mesh_vertices is not None and obj.mesh_faces is not None
    if nv < 4 or nf < 4:
        add(f"{f}.mesh", f"is empty or degenerate: {nv} vertices, {nf} faces (need >= 4 of each)")
        return
    if obj.mesh_faces.min() < 0 or obj.mesh_faces.max() >= nv:
        add(f"{f}.mesh.faces", f"index out of range [0, {nv})")
        return
    extent = np.ptp(obj.mesh_vertices, axis=0)
    if np.min(extent) < 1e-5:
        add(f"{f}.mesh", f"is degenerate (flat): bounding-box extents {extent.tolist()} m")
        return
    if np.max(extent) > 5.0:
        add(f"{f}.mesh", f"is {np.max(extent):.1f} m across; meshes must be in metres")
    v = obj.mesh_vertices[obj.mesh_faces]
    areas = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    if areas.sum() < 1e-8:
        add(f"{f}.mesh", "is degenerate: total surface area is zero")


def _validate_parts(problems: list[FieldProblem], obj: ObjectSpec, articulation: object, t: int | None) -> None:
    """An articulated object's further parts (shape, mass, joint) and its recorded joint values."""
    if (why := text_problem(obj.base_part, MAX_NAME_CHARS)) is not None or not obj.base_part:
        problems.append(FieldProblem("object.base_part", why or "must not be empty"))
    for k, part in enumerate(obj.parts):
        if part.shape.parts:
            problems.append(FieldProblem(f"object.parts[{k}]", "a part holds no parts of its own (use joint.parent)"))
        _validate_object(problems, part.shape, f"object.parts[{k}]")
    validate_joints(problems, obj.joints, obj.part_names, articulation, t)


def _validate_hand(problems: list[FieldProblem], name: str, hand: HandTrack, t: int | None) -> None:
    add = lambda f, p: problems.append(FieldProblem(f, p))  # noqa: E731
    if hand.side not in ("right", "left"):
        add(f"{name}.side", f"must be 'right' or 'left', got {shown(hand.side)}")
    if hand.keypoints is None and hand.mano is None:
        add(name, "needs keypoints or MANO parameters")
    tv = _check_array(problems, f"{name}.valid", hand.valid, (None,))
    if tv is not None:
        if hand.valid.dtype != np.bool_:
            add(f"{name}.valid", f"must be boolean, got {hand.valid.dtype}")
        elif not hand.valid.any():
            add(f"{name}.valid", "no frame has a valid hand")
        if t is not None and tv != t:
            add(f"{name}.valid", f"has {tv} frames but object_pose has {t}")
    if hand.keypoints is not None:
        tk = _check_array(problems, f"{name}.keypoints", hand.keypoints, (None, NUM_JOINTS, 3))
        if tk is not None and t is not None and tk != t:
            add(f"{name}.keypoints", f"has {tk} frames but object_pose has {t}")
    if hand.mano is not None:
        m = hand.mano
        base = f"{name}.mano"
        for key, arr, shape in (
            ("global_orient", m.global_orient, (None, 3)),
            ("trans", m.trans, (None, 3)),
            ("hand_pose", m.hand_pose, (None, 45 if m.pose_format == "axis_angle" else None)),
            ("betas", m.betas, (None,)),
        ):
            n = _check_array(problems, f"{base}.{key}", arr, shape)
            if n is not None and key != "betas" and t is not None and n != t:
                add(f"{base}.{key}", f"has {n} frames but object_pose has {t}")
        if m.pose_format not in ("axis_angle", "pca"):
            add(f"{base}.pose_format", f"must be 'axis_angle' or 'pca', got {shown(m.pose_format)}")
        elif m.pose_format == "pca" and m.hand_pose.ndim == 2 and not 1 <= m.hand_pose.shape[1] <= 45:
            add(f"{base}.hand_pose", f"PCA needs 1-45 coefficients, got {m.hand_pose.shape[1]}")


def _is_real(x: object) -> bool:
    """A finite int or float (not a bool, not NaN/Inf)."""
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and bool(np.isfinite(x))


def _validate_rigid(problems: list[FieldProblem], name: str, mat: FloatArray) -> None:
    rot = mat[:3, :3]
    if np.abs(rot).max() > 2.0:  # a rotation's entries are within [-1, 1]; also keeps rot @ rot.T finite
        problems.append(FieldProblem(name, "upper-left 3x3 must be a rotation (entries within [-1, 1])"))
        return
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-4) or np.linalg.det(rot) < 0:
        problems.append(FieldProblem(name, "upper-left 3x3 must be a rotation (orthonormal, det +1)"))
    if not np.allclose(mat[3], [0, 0, 0, 1], atol=1e-9):
        problems.append(FieldProblem(name, "last row must be [0, 0, 0, 1]"))


def _rotation_taking(a: FloatArray, b: FloatArray) -> FloatArray:
    """Smallest rotation matrix taking unit vector a to unit vector b."""
    from scipy.spatial.transform import Rotation

    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        return Rotation.from_rotvec(np.pi * perp / np.linalg.norm(perp)).as_matrix()
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix()


def _transform_points(points: FloatArray, pose: FloatArray) -> FloatArray:
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_quat(pose[3:7], scalar_first=True).as_matrix()
    return points @ rot.T + pose[:3]


def transform_poses(world_from_source: FloatArray, poses: FloatArray) -> FloatArray:
    """Apply a 4x4 rigid transform to (T, 7) poses; quaternions come out sign-continuous, qw0 >= 0."""
    from scipy.spatial.transform import Rotation

    rot_w = world_from_source[:3, :3]
    out = np.empty_like(poses, dtype=np.float64)
    out[:, :3] = poses[:, :3] @ rot_w.T + world_from_source[:3, 3]
    rots = Rotation.from_matrix(rot_w) * Rotation.from_quat(poses[:, 3:7], scalar_first=True)
    quats = rots.as_quat(scalar_first=True)
    for i in range(1, len(quats)):
        if np.dot(quats[i], quats[i - 1]) < 0:
            quats[i] = -quats[i]
    if len(quats) and quats[0, 0] < 0:
        quats = -quats
    out[:, 3:] = quats
    return out
