"""Points covering a primitive object's surface (``object_surface_points``; a mesh keeps its own vertices).

The refinement measures hand-to-object distances against surface points (``worker.refine.prepare``: contact
targets, the grasp-reach table) and finds the hand's approach by them (``worker.simulation.rest_pose``). A mesh
gives its vertices, edge midpoints and face centroids; a primitive's tessellation alone would give a box's 8
corners and a cylinder's two rims, so a fingertip on the middle of a face would read the distance to a corner. Here
every face is covered by a grid at most ``SPACING_M`` apart (coarser for a very large primitive, so a few
``MAX_POINTS`` points at most), plus the tessellation's vertices themselves, so the lowest point of the surface
(the table is laid there) is the same as before.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from common.geometry import FloatArray

if TYPE_CHECKING:
    from common.sequence import ObjectSpec

#: Largest gap between neighbouring points: well under the 1 cm contact threshold of the refinement's terms.
SPACING_M = 0.005
#: Upper bound on the number of points (a large primitive gets a coarser grid instead).
MAX_POINTS = 20_000
#: Largest gap between the points sampled on an articulated object's part meshes (``part_surface_points``).
MESH_SPACING_M = 0.005


def object_surface_points(obj: ObjectSpec, spacing: float = SPACING_M) -> FloatArray:
    """An object's surface points in its frame: a mesh's vertices; a primitive's tessellation vertices and, with
    ``spacing`` > 0, ``primitive_surface_points`` (``SimConfig.primitive_surface_spacing_m``; 0 reproduces results
    made before these points existed)."""
    verts = obj.surface_vertices()
    if obj.is_mesh or spacing <= 0:
        return verts
    assert obj.primitive is not None and obj.size is not None
    return np.concatenate([verts, primitive_surface_points(obj.primitive, obj.size, spacing)])


def posed_surface_points(obj: ObjectSpec, values: FloatArray | None, spacing: float = SPACING_M) -> FloatArray:
    """The surface points of every part of an articulated object (``part_surface_points``), in the base part's
    frame with its joints at ``values`` (J,); a rigid object's own ``object_surface_points``."""
    if not obj.parts:
        return object_surface_points(obj, spacing)
    from common.geometry import quat_rotate

    assert values is not None
    poses = obj.part_poses(np.array([0.0, 0, 0, 1, 0, 0, 0]), np.asarray(values, dtype=np.float64))
    chunks = [quat_rotate(poses[k, 3:], part_surface_points(shape, spacing)) + poses[k, :3]
              for k, shape in enumerate(obj.part_shapes())]  # fmt: skip
    return np.concatenate(chunks)


def part_surface_points(shape: ObjectSpec, spacing: float = SPACING_M) -> FloatArray:
    """An articulated object's part: a primitive's ``object_surface_points``, a mesh's vertices plus every triangle
    covered by a grid at most ``MESH_SPACING_M`` apart (``mesh_surface_points``). Parts get the dense mesh
    sampling because part meshes come coarse (ARCTIC's have edges up to 12 cm, where vertices alone read a
    fingertip on a face as centimetres away); a rigid object keeps its vertices (``object_surface_points``), as the
    figures of bench/results/refine_dev120.md were made with."""
    if shape.mesh_vertices is None or shape.mesh_faces is None:
        return object_surface_points(shape, spacing)
    return mesh_surface_points(shape.mesh_vertices, shape.mesh_faces, MESH_SPACING_M)


def mesh_surface_points(vertices: FloatArray, faces: np.ndarray, spacing: float) -> FloatArray:
    """(N, 3) a mesh's vertices and points covering each triangle at most ``spacing`` apart (a barycentric grid of
    n + 1 points along its longest edge), coarser for a large mesh so ``MAX_POINTS`` bounds the count."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]  # (F, 3, 3)
    longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    area = float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
    spacing = max(spacing, float(np.sqrt(area / MAX_POINTS)))
    out = [np.asarray(vertices, dtype=np.float64)]
    steps = np.ceil(longest / spacing).astype(np.int64)
    for n in np.unique(steps[steps >= 2]):
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        bary = np.stack([i[keep], j[keep], n - i[keep] - j[keep]], axis=1) / n  # (P, 3) barycentric weights
        out.append(np.einsum("pk,fkd->fpd", bary, tri[steps == n]).reshape(-1, 3))
    return np.concatenate(out)


def primitive_surface_points(kind: str, size: FloatArray, spacing: float = SPACING_M) -> FloatArray:
    """(N, 3) points on the surface of a primitive in its own frame (``ObjectSpec`` conventions: box half-extents;
    cylinder/capsule radius and half-length along z; sphere radius)."""
    if kind not in ("box", "cylinder", "sphere", "capsule"):
        raise ValueError(f"unknown primitive {kind!r}")
    s = np.asarray(size, dtype=np.float64)
    area = _area(kind, s)
    spacing = max(spacing, float(np.sqrt(area / MAX_POINTS)))
    if kind == "box":
        return _box(s, spacing)
    if kind == "cylinder":
        return _cylinder(s[0], s[1], spacing)
    if kind == "sphere":
        return _sphere_patch(s[0], spacing, np.zeros(3), hemisphere=0)
    side = _cylinder_side(s[0], s[1], spacing)  # a capsule
    top = _sphere_patch(s[0], spacing, np.array([0.0, 0.0, s[1]]), hemisphere=1)
    bottom = _sphere_patch(s[0], spacing, np.array([0.0, 0.0, -s[1]]), hemisphere=-1)
    return np.concatenate([side, top, bottom])


def _area(kind: str, s: FloatArray) -> float:
    if kind == "box":
        return float(8 * (s[0] * s[1] + s[1] * s[2] + s[0] * s[2]))
    if kind == "cylinder":
        return float(2 * np.pi * s[0] * (2 * s[1]) + 2 * np.pi * s[0] ** 2)
    if kind == "sphere":
        return float(4 * np.pi * s[0] ** 2)
    return float(2 * np.pi * s[0] * (2 * s[1]) + 4 * np.pi * s[0] ** 2)


def _grid(lo: float, hi: float, spacing: float) -> FloatArray:
    """Points from ``lo`` to ``hi`` inclusive, at most ``spacing`` apart."""
    return np.linspace(lo, hi, max(2, int(np.ceil((hi - lo) / spacing)) + 1))


def _box(h: FloatArray, spacing: float) -> FloatArray:
    faces = []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        gu, gv = np.meshgrid(_grid(-h[u], h[u], spacing), _grid(-h[v], h[v], spacing), indexing="ij")
        for sign in (-1.0, 1.0):
            pts = np.zeros((gu.size, 3))
            pts[:, axis], pts[:, u], pts[:, v] = sign * h[axis], gu.ravel(), gv.ravel()
            faces.append(pts)
    return np.unique(np.concatenate(faces), axis=0)


def _ring(radius: float, z: float, spacing: float) -> FloatArray:
    n = max(8, int(np.ceil(2 * np.pi * radius / spacing)))
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(a), radius * np.sin(a), np.full(n, z)], axis=1)


def _cylinder_side(radius: float, half: float, spacing: float) -> FloatArray:
    return np.concatenate([_ring(radius, z, spacing) for z in _grid(-half, half, spacing)])


def _cylinder(radius: float, half: float, spacing: float) -> FloatArray:
    caps = []
    for z in (-half, half):
        caps.append(np.array([[0.0, 0.0, z]]))
        caps += [_ring(r, z, spacing) for r in _grid(0.0, radius, spacing)[1:]]
    return np.concatenate([_cylinder_side(radius, half, spacing), *caps])


def _sphere_patch(radius: float, spacing: float, centre: FloatArray, hemisphere: int) -> FloatArray:
    """Rings of latitude ``spacing`` apart on a sphere (``hemisphere`` 1: z >= 0 only, -1: z <= 0, 0: whole)."""
    lo, hi = {0: (-np.pi / 2, np.pi / 2), 1: (0.0, np.pi / 2), -1: (-np.pi / 2, 0.0)}[hemisphere]
    rings = []
    for lat in _grid(lo, hi, spacing / radius):
        r, z = radius * np.cos(lat), radius * np.sin(lat)
        rings.append(np.array([[0.0, 0.0, z]]) if r < 1e-9 else _ring(r, z, spacing))
    return np.concatenate(rings) + centre
