"""A primitive object's surface points (``common.primitive_surface``): on the surface, covering every face, bounded
in number, and the tessellation alone with spacing 0 (results made before them)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from common.primitive_surface import MAX_POINTS, SPACING_M, object_surface_points, primitive_surface_points
from common.sequence import ObjectSpec

RNG = np.random.default_rng(7)


def _on_surface(kind: str, size: np.ndarray, n: int = 4000) -> np.ndarray:
    """Points drawn on the analytic surface (every face / cap / side, not the corners only)."""
    if kind == "box":
        p = RNG.uniform(-1, 1, (n, 3)) * size
        axis = RNG.integers(0, 3, n)
        p[np.arange(n), axis] = np.sign(RNG.uniform(-1, 1, n)) * size[axis]
        return p
    r, half = size[0], size[-1] if kind != "sphere" else 0.0
    d = RNG.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if kind == "sphere":
        return r * d
    if kind == "capsule":
        return r * d + np.where(d[:, 2:] >= 0, 1.0, -1.0) * np.array([0.0, 0.0, half])
    a = RNG.uniform(0, 2 * np.pi, n)
    side = np.stack([r * np.cos(a), r * np.sin(a), RNG.uniform(-half, half, n)], 1)
    rr = r * np.sqrt(RNG.uniform(0, 1, n))
    cap = np.stack([rr * np.cos(a), rr * np.sin(a), np.sign(RNG.uniform(-1, 1, n)) * half], 1)
    return np.where(RNG.uniform(0, 1, (n, 1)) < 0.5, side, cap)


def _signed_distance(kind: str, size: np.ndarray, p: np.ndarray) -> np.ndarray:
    if kind == "box":
        q = np.abs(p) - size
        return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    if kind == "sphere":
        return np.linalg.norm(p, axis=1) - size[0]
    if kind == "capsule":
        z = np.clip(p[:, 2], -size[1], size[1])
        return np.linalg.norm(p - np.stack([0 * z, 0 * z, z], 1), axis=1) - size[0]
    radial, axial = np.linalg.norm(p[:, :2], axis=1) - size[0], np.abs(p[:, 2]) - size[1]
    q = np.stack([radial, axial], 1)
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


CASES = [("box", [0.05, 0.03, 0.02]), ("box", [0.004, 0.1, 0.05]), ("cylinder", [0.034, 0.05]),
         ("cylinder", [0.01, 0.06]), ("sphere", [0.04]), ("capsule", [0.02, 0.05])]


@pytest.mark.parametrize(("kind", "size"), CASES)
def test_points_lie_on_the_surface_and_cover_it_within_the_spacing(kind: str, size: list[float]) -> None:
    s = np.asarray(size)
    pts = primitive_surface_points(kind, s)
    assert np.abs(_signed_distance(kind, s, pts)).max() < 1e-9
    # Any point of the surface has a sample within the grid's half diagonal (a ring's chord and the gap between
    # rings are each at most the spacing; on a sphere the chord of a latitude step is a little shorter).
    gap, _ = cKDTree(pts).query(_on_surface(kind, s))
    assert gap.max() <= SPACING_M * np.sqrt(2) / 2 + 1e-9, (kind, gap.max())


def test_the_box_example_gets_points_on_its_faces_not_only_corners() -> None:
    box = ObjectSpec(name="box", mass_kg=0.2, primitive="box", size=np.array([0.04, 0.03, 0.05]))
    corners = object_surface_points(box, 0.0)
    dense = object_surface_points(box, SPACING_M)
    assert len(corners) == 8 and np.array_equal(corners, box.surface_vertices())
    face_centre = np.array([[0.04, 0.0, 0.0]])
    assert cKDTree(corners).query(face_centre)[0][0] > 0.05  # what a fingertip on the face read before
    assert cKDTree(dense).query(face_centre)[0][0] < 1e-9
    assert dense[:, 2].min() == corners[:, 2].min()  # the table is laid under the same lowest point


def test_a_large_primitive_gets_a_coarser_grid_not_unbounded_points() -> None:
    pts = primitive_surface_points("box", np.array([1.0, 1.0, 0.5]))
    assert len(pts) <= 1.2 * MAX_POINTS


def test_meshes_are_unchanged() -> None:
    verts = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], dtype=np.float64)
    mesh = ObjectSpec(name="tet", mass_kg=0.1, mesh_vertices=verts,
                      mesh_faces=np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
    assert object_surface_points(mesh) is verts


def test_unknown_primitive_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown primitive"):
        primitive_surface_points("cone", np.array([0.1]))


def test_the_refinement_reads_the_configured_points() -> None:
    from worker.example.sequences import short_example_sequence
    from worker.refine.prepare import _surface_samples

    seq = short_example_sequence()
    assert np.array_equal(_surface_samples(seq.object, 0.0), seq.object.surface_vertices())  # the default: as before
    dense = _surface_samples(seq.object, SPACING_M)
    assert len(dense) > 100 * len(seq.object.surface_vertices())
