"""The table under the recorded frame-0 object (worker.simulation.support_plane)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from worker.simulation.support_plane import SupportPlane, support_candidates


def _box_vertices(half: tuple[float, float, float], rounded: bool = False) -> np.ndarray:
    hx, hy, hz = half
    corners = np.array([[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    if not rounded:
        return corners
    # Bevel every corner with points along a small sphere: the hull then has tiny facets of every orientation,
    # among them some exactly level that the box could never rest on.
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = 0.004
    inner = corners * (1 - r / np.array(half))
    pts = [c + r * d[np.all(np.sign(d) == np.sign(c), axis=1)] for c in inner]
    return np.concatenate(pts)


def _posed(verts: np.ndarray, rotvec: tuple[float, float, float], pos: tuple[float, float, float]) -> np.ndarray:
    return np.asarray(Rotation.from_rotvec(rotvec).apply(verts) + np.array(pos))


@pytest.mark.parametrize("rounded", [False, True])
def test_tilted_box_rests_on_its_bottom_face(rounded: bool) -> None:
    tilt = np.radians(4.0)
    verts = _posed(_box_vertices((0.05, 0.03, 0.02), rounded), (tilt, 0.0, 0.0), (0.1, 0.2, 0.025))
    planes = support_candidates(verts, max_tilt_deg=10.0)
    assert planes  # the bottom face (and, rounded, maybe bevel facets that still hold the centre)
    plane = max(planes, key=lambda p: p.tilt_deg) if rounded else planes[0]
    assert plane.tilt_deg == pytest.approx(4.0, abs=0.05)
    expected_up = Rotation.from_rotvec((tilt, 0.0, 0.0)).apply([0.0, 0.0, 1.0])
    np.testing.assert_allclose(plane.normal, expected_up, atol=3e-3)  # within 0.2 deg
    # Every vertex is on or above the plane, and the plane touches the box.
    heights = (verts - plane.point) @ plane.normal
    assert heights.min() == pytest.approx(0.0, abs=1e-9)


def test_beyond_the_tilt_limit_there_is_no_support() -> None:
    verts = _posed(_box_vertices((0.05, 0.03, 0.02)), (np.radians(15.0), 0.0, 0.0), (0.0, 0.0, 0.03))
    assert support_candidates(verts, max_tilt_deg=10.0) == []
    (plane,) = support_candidates(verts, max_tilt_deg=20.0)
    assert plane.tilt_deg == pytest.approx(15.0, abs=0.05)


def test_lying_cylinder_offers_the_strip_under_its_centre() -> None:
    ang = np.linspace(0, 2 * np.pi, 48, endpoint=False) + 0.03  # no strip exactly level
    ring = np.column_stack([np.cos(ang), np.sin(ang)]) * 0.01
    verts = np.concatenate([np.column_stack([np.full(48, x), ring]) for x in (-0.07, 0.07)])  # axis along x
    verts[:, 2] += 0.01
    (plane,) = support_candidates(verts, max_tilt_deg=10.0)  # only one strip holds the centre
    assert plane.tilt_deg < 360 / 48 / 2 + 1e-6


def test_the_face_must_hold_the_given_centre_of_mass() -> None:
    """A non-convex body's mass centre is not its hull's: a face under the hull centroid that the real centre
    overhangs is no support (the body would tip off it), and the real centre decides."""
    verts = _posed(_box_vertices((0.05, 0.03, 0.02)), (np.radians(4.0), 0.0, 0.0), (0.1, 0.2, 0.025))
    centre = verts.mean(axis=0)
    (plane,) = support_candidates(verts, max_tilt_deg=10.0, centre_of_mass=centre + np.array([0.04, 0.0, 0.0]))
    assert plane.tilt_deg == pytest.approx(4.0, abs=0.05)
    assert support_candidates(verts, max_tilt_deg=10.0, centre_of_mass=centre + np.array([0.06, 0.0, 0.0])) == []


def _l_prism() -> Any:
    """A watertight L-shaped prism (10 x 10 cm arms 1 cm thick, 4 cm deep): a simple non-convex solid."""
    import trimesh

    outline = np.array([[0, 0], [10, 0], [10, 1], [1, 1], [1, 10], [0, 10]], dtype=float) / 100  # (x, z)
    n = len(outline)
    verts = np.array([[x, y, z] for y in (-0.02, 0.02) for x, z in outline])
    cap = [[0, i, i + 1] for i in range(1, n - 1)]  # a fan from the outer corner (vertex 0) covers the L
    faces = cap + [[n + a, n + c, n + b] for a, b, c in cap]
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, n + i, j], [j, n + i, n + j]]
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=True)
    mesh.fix_normals()
    assert mesh.is_watertight
    return mesh


def test_centre_of_mass_is_the_simulated_body_s() -> None:
    """The centre the table fit checks is the one MuJoCo gives the body: for an L-shaped solid, 1 cm from the
    centroid of its hull."""
    import mujoco
    from scipy.spatial import ConvexHull

    from common.sequence import ObjectSpec
    from worker.simulation.object_model import centre_of_mass, object_mjcf
    from worker.simulation.scene import SimConfig
    from worker.simulation.support_plane import _hull_centroid

    ell = _l_prism()
    obj = ObjectSpec(name="ell", mass_kg=0.2, mesh_vertices=np.asarray(ell.vertices), mesh_faces=np.asarray(ell.faces))
    mjcf = object_mjcf(obj, SimConfig(), np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    model = mujoco.MjModel.from_xml_string(
        f"<mujoco><asset>{mjcf.assets}</asset><worldbody>{mjcf.body}</worldbody></mujoco>")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    com = centre_of_mass(obj)
    np.testing.assert_allclose(data.xipos[-1], com, atol=1e-9)
    hull = ConvexHull(ell.vertices)
    assert np.linalg.norm(_hull_centroid(np.asarray(ell.vertices), hull.simplices) - com) > 0.01


def test_plane_quaternion_maps_z_to_the_normal() -> None:
    n = np.array([0.1, -0.05, 1.0])
    plane = SupportPlane(point=np.zeros(3), normal=n / np.linalg.norm(n), tilt_deg=0.0)
    q = plane.quat()
    rot = Rotation.from_quat(np.r_[q[1:], q[0]])
    np.testing.assert_allclose(rot.apply([0.0, 0.0, 1.0]), plane.normal, atol=1e-12)
    np.testing.assert_allclose(SupportPlane.level(0.2).quat(), [1.0, 0.0, 0.0, 0.0])


def test_bad_vertices_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match="vertices_world"):
        support_candidates(np.zeros((3, 3)), 10.0)
