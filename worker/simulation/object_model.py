"""MJCF of the manipulated object: a free body with the dataset mass and the mesh's inertia (DESIGN §1.4).

Primitives become one MuJoCo primitive geom (MuJoCo computes the inertia from the shape and the mass). Meshes
become their convex parts (``convex_cache``, as finely as ``SimConfig.convex_detail`` says) as collision geoms;
the inertia comes from the original watertight mesh (its convex hull when it is not watertight), scaled to the
dataset mass.

An articulated object (``common.articulation``) is a body tree: the base part is the free body ``object``, every
further part k a child body ``object_p{k+1}`` of its parent part's body, placed at its joint's origin, with a
``hinge`` or ``slide`` joint ``object_joint{k}`` on the joint's axis and limits (``SimConfig.articulation_*`` for
its damping and friction unless the file gives them). Geoms are numbered ``object_{i}`` over all parts in order.
Parts collide with the hands and the table, not with each other: MuJoCo leaves a parent and its child alone, and
the joint limits keep a lid out of its base.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.geometry import FloatArray, quat_rotate
from common.sequence import ObjectSpec
from worker.simulation.config import HAND_BIT, OBJECT_BIT, TABLE_BIT, SimConfig
from worker.simulation.convex_cache import CONVEX_DETAIL_PARAMS, convex_parts
from worker.simulation.hand_mjcf import fmt

OBJECT_BODY = "object"
OBJECT_JOINT = "object_root"
GRAVITY = 9.81
#: The weld that holds the object before the hand arrives (``SimConfig.hold_until_m``).
OBJECT_HOLD = "object_hold"


@dataclass(frozen=True)
class ObjectMjcf:
    """The object's MJCF pieces and how its collision shape was made. ``part_geoms``: the number of geoms of each
    part, base first (one entry for a rigid object)."""

    assets: str
    body: str
    num_geoms: int
    collision: str  # "primitive", "hull", "coacd" or "cache"
    part_geoms: tuple[int, ...] = ()


def part_body_name(k: int) -> str:
    """The body of part k (0: the base, ``OBJECT_BODY``)."""
    return OBJECT_BODY if k == 0 else f"{OBJECT_BODY}_p{k}"


def joint_name(k: int) -> str:
    """The joint of further part k (0-based over ``ObjectSpec.parts``)."""
    return f"{OBJECT_BODY}_joint{k}"


def mesh_inertia(vertices: FloatArray, faces: np.ndarray, mass: float) -> tuple[FloatArray, FloatArray]:
    """Centre of mass (3,) and inertia tensor about it (3,3) of a solid mesh of the given mass."""
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    if not mesh.is_watertight or abs(float(mesh.volume)) < 1e-12:
        mesh = mesh.convex_hull
    volume = abs(float(mesh.volume))
    if volume < 1e-12:
        raise ValueError("object mesh has no volume; cannot compute its inertia")
    mesh.density = mass / volume
    if float(mesh.volume) < 0:  # inward-facing faces: flip so the tensor is positive definite
        mesh.invert()
    return np.asarray(mesh.center_mass, dtype=np.float64), np.asarray(mesh.moment_inertia, dtype=np.float64)


def centre_of_mass(obj: ObjectSpec) -> FloatArray:
    """Where the simulated body's mass centre is, in the object frame (a primitive's is its origin)."""
    if obj.mesh_vertices is None or obj.mesh_faces is None:
        return np.zeros(3)
    return mesh_inertia(obj.mesh_vertices, obj.mesh_faces, obj.mass_kg)[0]


def object_mjcf(
    obj: ObjectSpec, config: SimConfig, pos: FloatArray, quat: FloatArray, *, cache_dir: Path | None = None
) -> ObjectMjcf:
    """Assets and body XML of the object placed at ``pos`` (3,) / ``quat`` (4,) wxyz (its base part there)."""
    head = f'<body name="{OBJECT_BODY}" pos="{fmt(pos)}" quat="{fmt(quat)}">\n  <freejoint name="{OBJECT_JOINT}"/>'
    built: list[_ShapeXml] = []
    for k, shape in enumerate(obj.part_shapes()):
        built.append(_shape_xml(shape, config, sum(len(b.geoms) for b in built), cache_dir, index=k))
    assets = "\n".join(b.assets for b in built if b.assets)
    if not obj.parts:
        base = built[0]
        if base.inertial:
            body = "\n".join([head, base.inertial, *base.geoms, "</body>"])
        else:
            body = f"{head}\n" + "\n".join(base.geoms) + "\n</body>"
        return ObjectMjcf(assets=assets, body=body, num_geoms=len(base.geoms), collision=base.collision,
                          part_geoms=(len(base.geoms),))
    children: dict[int, list[int]] = {}
    for k, parent in enumerate(obj.parent_indices()):
        children.setdefault(parent, []).append(k + 1)
    friction = joint_friction(obj, config)

    def body_xml(i: int) -> list[str]:
        b = built[i]
        lines = [] if not b.inertial else [b.inertial]
        lines += b.geoms
        for c in children.get(i, []):
            j = obj.parts[c - 1].joint
            kind = "hinge" if j.kind == "revolute" else "slide"
            damping = config.articulation_damping if j.damping is None else j.damping
            lines.append(f'<body name="{part_body_name(c)}" pos="{fmt(j.origin_pos)}" quat="{fmt(j.origin_quat)}">')
            lines.append(f'  <joint name="{joint_name(c - 1)}" type="{kind}" axis="{fmt(j.axis)}" '
                         f'range="{fmt(j.limits)}" damping="{damping:.9g}" frictionloss="{friction[c - 1]:.9g}" '
                         f'solreffriction="{fmt(config.articulation_friction_solref)}" '
                         f'solimpfriction="{fmt(config.articulation_friction_solimp)}"/>')
            lines += ["  " + line for line in body_xml(c)]
            lines.append("</body>")
        return lines

    body = "\n".join([head, *body_xml(0), "</body>"])
    how = sorted({b.collision for b in built})
    return ObjectMjcf(assets=assets, body=body, num_geoms=sum(len(b.geoms) for b in built),
                      collision=how[0] if len(how) == 1 else "+".join(how),
                      part_geoms=tuple(len(b.geoms) for b in built))


@dataclass(frozen=True)
class _ShapeXml:
    assets: str
    geoms: list[str]
    inertial: str  # "" for a primitive: MuJoCo computes its inertia from the geom and ``mass``
    collision: str


def _shape_xml(shape: ObjectSpec, config: SimConfig, first: int, cache_dir: Path | None, index: int) -> _ShapeXml:
    """Geoms (and mesh assets, inertial) of one part, its geoms numbered from ``first``. Part 0's mesh assets keep
    the names a rigid object's always had (``object_part{i}``)."""
    friction = shape.friction if shape.friction is not None else config.object_friction
    common = (
        f'contype="{OBJECT_BIT}" conaffinity="{HAND_BIT | TABLE_BIT}" condim="{config.object_condim}" '
        f'friction="{friction:g} 0.005 0.0001" solref="{fmt(config.contact_solref)}" '
        f'solimp="{fmt(config.contact_solimp)}" group="2"'
    )
    if shape.primitive is not None:
        assert shape.size is not None
        size = shape.size
        if shape.primitive == "sphere":
            size_attr = f"{size[0]:.9g}"
        elif shape.primitive == "box":
            size_attr = fmt(size)
        else:
            size_attr = f"{size[0]:.9g} {size[1]:.9g}"
        geom = (f'  <geom name="object_{first}" type="{shape.primitive}" size="{size_attr}" '
                f'mass="{shape.mass_kg:.9g}" {common}/>')
        return _ShapeXml("", [geom], "", "primitive")
    assert shape.mesh_vertices is not None and shape.mesh_faces is not None
    parts, how = convex_parts(shape.mesh_vertices, shape.mesh_faces, cache_dir=cache_dir,
                              params=CONVEX_DETAIL_PARAMS[config.convex_detail])
    com, inertia = mesh_inertia(shape.mesh_vertices, shape.mesh_faces, shape.mass_kg)
    full = [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]]
    assets, geoms = [], []
    prefix = "object_part" if index == 0 else f"object_p{index}_part"
    for i, part in enumerate(parts):
        assets.append(f'<mesh name="{prefix}{i}" vertex="{fmt(part)}"/>')
        geoms.append(f'  <geom name="object_{first + i}" type="mesh" mesh="{prefix}{i}" {common}/>')
    inertial = f'  <inertial pos="{fmt(com)}" mass="{shape.mass_kg:.9g}" fullinertia="{fmt(full)}"/>'
    return _ShapeXml("\n".join(assets), geoms, inertial, how)


def joint_friction(obj: ObjectSpec, config: SimConfig) -> list[float]:
    """Each joint's dry friction: the file's value, else ``config.articulation_friction_factor`` times the largest
    gravity load it carries (``SimConfig.articulation_friction_factor``), from the parts' masses and centres of
    mass at joint value 0."""
    out = []
    poses = obj.part_poses(np.array([0.0, 0, 0, 1, 0, 0, 0]), np.zeros(len(obj.parts)))
    shapes = obj.part_shapes()
    coms = [quat_rotate(poses[i, 3:], centre_of_mass(shapes[i])) + poses[i, :3] for i in range(len(shapes))]
    parents = obj.parent_indices()
    for k, part in enumerate(obj.parts):
        if part.joint.friction is not None:
            out.append(float(part.joint.friction))
            continue
        subtree = _subtree(parents, k + 1)
        mass = sum(shapes[i].mass_kg for i in subtree)
        com = sum(shapes[i].mass_kg * coms[i] for i in subtree) / mass
        axis_world = quat_rotate(poses[k + 1, 3:], np.asarray(part.joint.axis))
        if part.joint.kind == "revolute":
            arm = com - poses[k + 1, :3]
            reach = float(np.linalg.norm(arm - np.dot(arm, axis_world) * axis_world))
            load = mass * GRAVITY * reach
        else:
            load = mass * GRAVITY
        out.append(config.articulation_friction_factor * load)
    return out


def _subtree(parents: list[int], root: int) -> list[int]:
    """Part indices (0: base) of ``root`` and everything hung from it."""
    out = [root]
    for k, p in enumerate(parents):
        if p in out:
            out.append(k + 1)
    return out


def object_hold_xml(config: SimConfig) -> str:
    """The object welded to the world where the model places it (no ``relpose``: its pose in ``qpos0``), inactive
    until a rollout switches it on; as stiff as the wrist welds."""
    return (
        f'<weld name="{OBJECT_HOLD}" body1="{OBJECT_BODY}" active="false" '
        f'solref="{fmt(config.weld_solref)}" solimp="{fmt(config.weld_solimp)}"/>'
    )
