"""The grasp-reach loss (worker.refine.losses) and what it is built from: the object's distance table
(worker.refine.distance_grid), the fingers' distal segments and the grip frames (worker.refine.prepare)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from scipy.spatial import cKDTree

from worker.hand.model import FINGER_BASE_KEYPOINT, default_geometry
from worker.refine.distance_grid import DistanceGrid
from worker.refine.losses import (
    POS_SCALE,
    REACH_CAP,
    REACH_TOLERANCE,
    DistalSegments,
    HandKeypointTargets,
    WindowRecord,
    hand_terms,
)
from worker.refine.prepare import distal_segments, grip_frames
from worker.simulation.config import SimConfig
from worker.simulation.hand_mjcf import hand_mjcf, segment_body_name


def _box_surface(half: float = 0.02, n: int = 41) -> np.ndarray:
    """Points on the faces of a cube of half-size ``half`` (object frame), about 1 mm apart."""
    g = np.linspace(-half, half, n)
    a, b = np.meshgrid(g, g)
    faces = []
    for axis in range(3):
        for sign in (-half, half):
            p = np.zeros((a.size, 3))
            p[:, axis] = sign
            p[:, [k for k in range(3) if k != axis]] = np.column_stack([a.ravel(), b.ravel()])
            faces.append(p)
    return np.concatenate(faces)


def test_distance_grid_reads_the_sampled_surface_distance_within_its_tolerance() -> None:
    surface = _box_surface()
    grid = DistanceGrid(surface, margin=0.03)
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.05, 0.05, (2000, 3))
    exact, _ = cKDTree(surface).query(points)
    read = grid(points)
    assert read.shape == (2000,)
    assert np.abs(read - exact).max() <= grid.tolerance
    nodes = grid.lo + grid.spacing * np.array([[3, 4, 5], [10, 0, 7]])
    np.testing.assert_allclose(grid(nodes), cKDTree(surface).query(nodes)[0], atol=1e-12)  # exact at the nodes
    # Shapes pass through, and far beyond the table the reading keeps growing with the distance.
    assert grid(points.reshape(40, 50, 3)).shape == (40, 50)
    far = grid(np.array([[0.3, 0.0, 0.0], [0.6, 0.0, 0.0]]))
    assert far[0] == pytest.approx(0.28, abs=grid.tolerance) and far[1] == pytest.approx(0.58, abs=grid.tolerance)


def _distal() -> DistalSegments:
    base = np.asarray(FINGER_BASE_KEYPOINT)
    return DistalSegments(tuple(int(b) for b in base + 2), tuple(int(b) for b in base + 3), np.ones(5),
                          np.full(5, 0.008))


def _hand_on_box(gaps_mm: list[float], frames: int = 3) -> np.ndarray:
    """(F, 21, 3) keypoints whose distal capsules (radius 8 mm) lie flat ``gaps_mm`` above the cube's top face
    (z = 2 cm), one finger beside the next; the other keypoints far off."""
    kp = np.full((frames, 21, 3), 0.5)
    for f, gap in enumerate(gaps_mm):
        z = 0.02 + 0.008 + gap / 1000
        y = -0.016 + 0.008 * f
        kp[:, FINGER_BASE_KEYPOINT[f] + 2] = [-0.01, y, z]
        kp[:, FINGER_BASE_KEYPOINT[f] + 3] = [0.01, y, z]
    return kp


def _reach(keypoints: np.ndarray, grip: np.ndarray, grid: DistanceGrid) -> np.ndarray:
    c, f = keypoints.shape[:2]
    rec = WindowRecord(frames=np.arange(f), obj_pos=np.zeros((c, f, 3)), obj_quat=np.tile([1.0, 0, 0, 0], (c, f, 1)),
                       obj_vel=np.zeros((c, f, 6)), keypoints={"right": keypoints},
                       hinge_vel={"right": np.zeros((c, f, 45))}, offsets={"right": np.zeros((c, f + 1, 2))})
    ref = HandKeypointTargets(np.zeros((f, 21, 3)), np.ones(f, dtype=bool), (4, 8, 12, 16, 20),
                              np.zeros((f, 5), dtype=bool), np.zeros((f, 5, 3)), grip=grip, distal=_distal(),
                              surface=grid)
    return hand_terms(rec, "right", ref)["grasp_reach"]


def test_grasp_reach_charges_the_thumb_and_the_nearest_other_finger_on_grip_frames() -> None:
    grid = DistanceGrid(_box_surface(), margin=0.05, max_nodes=101)
    grip = np.array([False, True, True])
    touching = _hand_on_box([0.0, 0.0, 30.0, 30.0, 30.0])  # thumb and index on the face
    thumb_open = _hand_on_box([12.0, 0.0, 30.0, 30.0, 30.0])
    both_open = _hand_on_box([12.0, 8.0, 20.0, 30.0, 30.0])
    far = _hand_on_box([200.0, 200.0, 200.0, 200.0, 200.0])
    got = _reach(np.stack([touching, thumb_open, both_open, far]), grip, grid)
    per_frame = [
        0.0,
        (0.012 - REACH_TOLERANCE) / POS_SCALE,
        (0.012 - REACH_TOLERANCE + 0.008 - REACH_TOLERANCE) / POS_SCALE,  # the index is the nearest other finger
        2 * REACH_CAP / POS_SCALE,  # a hand that has lost the object is not pulled back across the scene
    ]
    np.testing.assert_allclose(got, 2 * np.array(per_frame), atol=2 * 2 * grid.tolerance / POS_SCALE)
    assert got[0] == 0.0 and got[1] < got[2] < got[3]
    # Frames where the hand need not hold the object cost nothing, and without a grip the term is off.
    np.testing.assert_array_equal(_reach(np.stack([both_open]), np.zeros(3, dtype=bool), grid), [0.0])


def test_grip_frames_start_a_lead_before_the_object_moves_and_need_a_touching_hand() -> None:
    t = 12
    pose = np.tile([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (t, 1))
    pose[6:, 2] = 0.01 * np.arange(1, t - 5)  # moves from frame 6 on
    touching = np.ones((t, 5), dtype=bool)
    np.testing.assert_array_equal(np.nonzero(grip_frames(pose, touching))[0], np.arange(6, t))
    np.testing.assert_array_equal(np.nonzero(grip_frames(pose, touching, lead=3))[0], np.arange(3, t))
    touching[9:] = False  # the recorded hand lets go
    np.testing.assert_array_equal(np.nonzero(grip_frames(pose, touching, lead=3))[0], np.arange(3, 9))
    assert not grip_frames(pose[:1].repeat(t, axis=0), np.ones((t, 5), dtype=bool)).any()  # never moves


def test_distal_segments_are_the_capsules_the_simulated_hand_is_built_with() -> None:
    geometry = default_geometry("left")
    distal = distal_segments(geometry)
    model = mujoco.MjModel.from_xml_string(hand_mjcf(geometry, SimConfig()))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    for f in range(5):
        geom = model.geom(segment_body_name("left", f, 2))
        assert geom.type == mujoco.mjtGeom.mjGEOM_CAPSULE
        assert geom.size[0] == pytest.approx(distal.radius[f])
        dip = data.site_xpos[model.site(f"left_kp{distal.dip[f]}").id]
        tip = data.site_xpos[model.site(f"left_kp{distal.tip[f]}").id]
        # The capsule's axis runs from the DIP keypoint over end_fraction of the way to the tip keypoint.
        half_length = geom.size[1]
        assert 2 * half_length == pytest.approx(distal.end_fraction[f] * np.linalg.norm(tip - dip), rel=1e-6)
        np.testing.assert_allclose(data.geom_xpos[geom.id], dip + distal.end_fraction[f] * (tip - dip) / 2, atol=1e-9)
