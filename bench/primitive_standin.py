"""Real motions with primitive objects: a DexYCB sequence whose object is replaced by its tightest enclosing box or
cylinder (``bench/refine.py --as-primitive``).

A user's sequence may give its object as a primitive (``ObjectSpec.primitive``; the built-in example is a box),
and the refinement prepares such objects along another path than meshes (their surface points are generated, not
read from the mesh). DexYCB has only meshes, so this benchmark builds the primitive case from real recordings:
for an object whose oriented bounding box or bounding cylinder holds at most ``MAX_VOLUME_RATIO`` times its convex
hull's volume (the boxes, cans and the large marker of YCB), the primitive replaces the mesh, and the recorded
object pose is re-expressed for the primitive's frame (its centre and axes: a cylinder along its z axis), so the
object stays where it was recorded. Hands, mass and friction are the sequence's own.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import trimesh

from common.geometry import FloatArray, matrix_to_quat, quat_mul, quat_rotate
from common.sequence import ObjectSpec, Sequence

#: A primitive replaces the mesh only where it fits this snugly (volume over the mesh's convex hull volume).
MAX_VOLUME_RATIO = 1.15


def primitive_standin(obj: ObjectSpec) -> tuple[ObjectSpec, FloatArray] | None:
    """The tighter of the mesh's oriented bounding box and bounding cylinder as a primitive ``ObjectSpec``, with
    the (4, 4) transform from the primitive's frame to the mesh's; None when neither fits within
    ``MAX_VOLUME_RATIO`` (or the object is a primitive already)."""
    if obj.mesh_vertices is None or obj.mesh_faces is None:
        return None
    mesh = trimesh.Trimesh(obj.mesh_vertices, obj.mesh_faces, process=False)
    hull_volume = float(mesh.convex_hull.volume)
    box, cylinder = mesh.bounding_box_oriented, mesh.bounding_cylinder
    if box.volume <= cylinder.volume:
        kind, volume = "box", float(box.volume)
        size = np.asarray(box.primitive.extents, dtype=np.float64) / 2
        transform = np.asarray(box.primitive.transform, dtype=np.float64)
    else:
        kind, volume = "cylinder", float(cylinder.volume)
        size = np.array([cylinder.primitive.radius, cylinder.primitive.height / 2], dtype=np.float64)
        transform = np.asarray(cylinder.primitive.transform, dtype=np.float64)
    if volume > MAX_VOLUME_RATIO * hull_volume:
        return None
    standin = ObjectSpec(name=f"{obj.name}_as_{kind}", mass_kg=obj.mass_kg, primitive=kind,  # type: ignore[arg-type]
                         size=size, friction=obj.friction)
    return standin, transform


def primitive_sequence(seq: Sequence) -> Sequence | None:
    """``seq`` with its object replaced by ``primitive_standin`` (None where no primitive fits): the recorded
    pose of the mesh frame composed with the primitive's offset, per frame."""
    fit = primitive_standin(seq.object)
    if fit is None:
        return None
    standin, mesh_from_primitive = fit
    pose = seq.object_pose
    offset_quat = matrix_to_quat(mesh_from_primitive[:3, :3])
    pos = pose[:, :3] + quat_rotate(pose[:, 3:], np.broadcast_to(mesh_from_primitive[:3, 3], pose[:, :3].shape))
    quat = quat_mul(pose[:, 3:], np.broadcast_to(offset_quat, pose[:, 3:].shape))
    return replace(seq, object=standin, object_pose=np.concatenate([pos, quat], axis=1))
