"""The table under the object at frame 0: a plane on which the recorded start pose is a resting pose.

Every DexYCB-style sequence starts with the object resting on the table, but the recorded frame-0 pose is a
vision estimate: the per-subject table plane is fitted with millimetres of spread and the object's rotation is
off by a few degrees (a box "resting" 4 degrees tilted on one edge). Dropped onto a level table at z = 0, such an
object falls flat during the settle, so the simulation starts a few degrees and millimetres away from the record,
and the grasp then carries that offset through the whole lift.

``support_candidates`` lists the planes that could lie under the object as recorded: faces of the convex hull
of the frame-0 object within ``max_tilt_deg`` of level that hold its centre of mass. Gravity stays -z; only the
table's plane would move, by the size of the annotation error (a few degrees, a few millimetres) or, for an object
recorded leaning on another that is not simulated, by its lean; friction holds it without sliding (tan 25 deg =
0.47, below the table friction of 0.8). ``table_fit`` picks one by simulation (or a level table when none
keeps the object still).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from common.geometry import FloatArray


@dataclass(frozen=True)
class SupportPlane:
    """A table plane through ``point`` with unit upward ``normal``; ``tilt_deg`` from level."""

    point: FloatArray
    normal: FloatArray
    tilt_deg: float

    def quat(self) -> FloatArray:
        """wxyz rotation taking +z to ``normal`` (the MuJoCo plane geom's frame)."""
        z = np.array([0.0, 0.0, 1.0])
        axis = np.cross(z, self.normal)
        s = float(np.linalg.norm(axis))
        c = float(np.dot(z, self.normal))
        if s < 1e-12:
            return np.array([1.0, 0.0, 0.0, 0.0])
        half = 0.5 * np.arctan2(s, c)
        return np.r_[np.cos(half), np.sin(half) * axis / s]

    def to_dict(self) -> dict[str, Any]:
        return {"point": self.point.tolist(), "normal": self.normal.tolist(), "tilt_deg": self.tilt_deg}

    @classmethod
    def level(cls, height: float = 0.0) -> SupportPlane:
        return cls(point=np.array([0.0, 0.0, height]), normal=np.array([0.0, 0.0, 1.0]), tilt_deg=0.0)


def support_candidates(
    vertices_world: FloatArray, max_tilt_deg: float, limit: int = 6, centre_of_mass: FloatArray | None = None
) -> list[SupportPlane]:
    """Faces of ``vertices_world`` (N, 3) the object could rest on as recorded, most nearly level first.

    Candidates are the faces of the convex hull (exactly coplanar triangles merged) whose outward normal is
    within ``max_tilt_deg`` of straight down and that hold the centre of mass: the vertical through it meets
    the face (a box's bottom, not the tiny facets of its rounded edges, which it would tip off). Whether the
    body then really stays put (a lying cylinder balanced on one narrow strip of its polygonal side does not)
    is for ``worker.simulation.table_fit`` to find out by simulation.

    ``centre_of_mass`` (world, 3) is where the simulated body's mass is: for a non-convex object (banana, clamp,
    pitcher) the solid mesh's centre lies 7-24 mm from its hull's, enough to pick a face the body tips off. Without
    it, the hull's volume centroid (right for a convex object) stands in.
    """
    from scipy.spatial import ConvexHull

    pts = np.asarray(vertices_world, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4:
        raise ValueError(f"vertices_world must be (N>=4, 3), got {pts.shape}")
    hull = ConvexHull(pts)
    com = _hull_centroid(pts, hull.simplices) if centre_of_mass is None else np.asarray(centre_of_mass, float)
    normals, offsets = hull.equations[:, :3], hull.equations[:, 3]
    tilts = np.degrees(np.arccos(np.clip(-normals[:, 2], -1.0, 1.0)))
    out: list[SupportPlane] = []
    seen = np.zeros(len(normals), dtype=bool)
    for i in np.flatnonzero(tilts <= max_tilt_deg)[np.argsort(tilts[tilts <= max_tilt_deg], kind="stable")]:
        if seen[i]:
            continue
        same = (normals @ normals[i] > 1 - 1e-9) & (np.abs(offsets - offsets[i]) < 1e-7)
        seen |= same
        foot = com - (normals[i] @ com + offsets[i]) / normals[i, 2] * np.array([0.0, 0.0, 1.0])
        if any(_in_triangle(foot, pts[t]) for t in hull.simplices[same]):
            out.append(SupportPlane(point=pts[hull.simplices[i]].mean(axis=0), normal=-normals[i],
                                    tilt_deg=float(tilts[i])))
            if len(out) >= limit:
                break
    return out


def _hull_centroid(pts: FloatArray, simplices: np.ndarray) -> FloatArray:
    """Volume centroid of a convex hull (uniform density: the centre of mass MuJoCo gives a convex body)."""
    inner = pts[np.unique(simplices)].mean(axis=0)
    tri = pts[simplices]  # (M, 3, 3)
    vol = np.abs(np.einsum("ij,ij->i", tri[:, 0] - inner, np.cross(tri[:, 1] - inner, tri[:, 2] - inner))) / 6
    cent = (tri.sum(axis=1) + inner) / 4
    return np.asarray((vol[:, None] * cent).sum(axis=0) / max(vol.sum(), 1e-18))


def _in_triangle(p: FloatArray, tri: FloatArray, eps: float = 1e-9) -> bool:
    """Whether p (on the triangle's plane) lies inside the triangle, by barycentric coordinates."""
    a, b, c = tri
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = v0 @ v0, v0 @ v1, v1 @ v1
    d20, d21 = v2 @ v0, v2 @ v1
    den = d00 * d11 - d01 * d01
    if den <= 0:
        return False
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return bool(v >= -eps and w >= -eps and v + w <= 1 + eps)
