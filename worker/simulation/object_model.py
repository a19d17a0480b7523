"""MJCF of the manipulated object: a free body with the dataset mass and the mesh's inertia (DESIGN §1.4).

Primitives become one MuJoCo primitive geom (MuJoCo computes the inertia from the shape and the mass). Meshes
become their convex parts (``convex_cache``, as finely as ``SimConfig.convex_detail`` says) as collision geoms;
the inertia comes from the original watertight mesh (its convex hull when it is not watertight), scaled to the
dataset mass.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.geometry import FloatArray
from common.sequence import ObjectSpec
from worker.simulation.config import HAND_BIT, OBJECT_BIT, TABLE_BIT, SimConfig
from worker.simulation.convex_cache import CONVEX_DETAIL_PARAMS, convex_parts
from worker.simulation.hand_mjcf import fmt

OBJECT_BODY = "object"
OBJECT_JOINT = "object_root"
#: The weld that holds the object before the hand arrives (``SimConfig.hold_until_m``).
OBJECT_HOLD = "object_hold"


@dataclass(frozen=True)
class ObjectMjcf:
    """The object's MJCF pieces and how its collision shape was made."""

    assets: str
    body: str
    num_geoms: int
    collision: str  # "primitive", "hull", "coacd" or "cache"


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
    """Assets and body XML of the object placed at ``pos`` (3,) / ``quat`` (4,) wxyz."""
    friction = obj.friction if obj.friction is not None else config.object_friction
    common = (
        f'contype="{OBJECT_BIT}" conaffinity="{HAND_BIT | TABLE_BIT}" condim="{config.object_condim}" '
        f'friction="{friction:g} 0.005 0.0001" solref="{fmt(config.contact_solref)}" '
        f'solimp="{fmt(config.contact_solimp)}" group="2"'
    )
    head = f'<body name="{OBJECT_BODY}" pos="{fmt(pos)}" quat="{fmt(quat)}">\n  <freejoint name="{OBJECT_JOINT}"/>'
    if obj.primitive is not None:
        assert obj.size is not None
        size = obj.size
        if obj.primitive == "sphere":
            size_attr = f"{size[0]:.9g}"
        elif obj.primitive == "box":
            size_attr = fmt(size)
        else:
            size_attr = f"{size[0]:.9g} {size[1]:.9g}"
        geom = f'  <geom name="object_0" type="{obj.primitive}" size="{size_attr}" mass="{obj.mass_kg:.9g}" {common}/>'
        return ObjectMjcf(assets="", body=f"{head}\n{geom}\n</body>", num_geoms=1, collision="primitive")

    assert obj.mesh_vertices is not None and obj.mesh_faces is not None
    parts, how = convex_parts(obj.mesh_vertices, obj.mesh_faces, cache_dir=cache_dir,
                              params=CONVEX_DETAIL_PARAMS[config.convex_detail])
    com, inertia = mesh_inertia(obj.mesh_vertices, obj.mesh_faces, obj.mass_kg)
    full = [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]]
    assets, geoms = [], []
    for i, part in enumerate(parts):
        assets.append(f'<mesh name="object_part{i}" vertex="{fmt(part)}"/>')
        geoms.append(f'  <geom name="object_{i}" type="mesh" mesh="object_part{i}" {common}/>')
    inertial = f'  <inertial pos="{fmt(com)}" mass="{obj.mass_kg:.9g}" fullinertia="{fmt(full)}"/>'
    body = "\n".join([head, inertial, *geoms, "</body>"])
    return ObjectMjcf(assets="\n".join(assets), body=body, num_geoms=len(parts), collision=how)


def object_hold_xml(config: SimConfig) -> str:
    """The object welded to the world where the model places it (no ``relpose``: its pose in ``qpos0``), inactive
    until a rollout switches it on; as stiff as the wrist welds."""
    return (
        f'<weld name="{OBJECT_HOLD}" body1="{OBJECT_BODY}" active="false" '
        f'solref="{fmt(config.weld_solref)}" solimp="{fmt(config.weld_solimp)}"/>'
    )
