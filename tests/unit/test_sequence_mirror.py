"""``common.sequence_mirror`` and the left hand as the right hand's mirror image (issue #15 item 5): the mirror
utility itself, the hand model, MJCF and retargeting under a reflection, and the control space mapping the same
coordinates to mirror-image controls for a sequence and its mirror."""

from __future__ import annotations

import re

import numpy as np
import pytest

from common.geometry import quat_to_matrix
from common.sequence import HandTrack, ObjectSpec, Sequence, Side
from common.sequence_mirror import mirror_object, mirror_sequence, reflection
from worker.example import short_example_sequence
from worker.hand.model import HINGE_NAMES, JOINT_LIMITS, MIRROR_SIGNS, default_geometry
from worker.simulation.config import SimConfig
from worker.simulation.hand_mjcf import hand_worldbody_xml

M = reflection()


def _mesh_sequence() -> Sequence:
    """A chiral (asymmetric) tetrahedron-ish mesh object and a right hand, in a tilted source frame."""
    base = short_example_sequence(errors=False)
    verts = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.03, 0.0], [0.0, 0.0, 0.02]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    world = np.eye(4)
    world[:3, :3] = quat_to_matrix(np.array([0.96, 0.1, -0.2, 0.15]))
    world[:3, 3] = [0.1, -0.2, 0.3]
    inv = np.linalg.inv(world)
    kp = base.keypoints_world(base.hands[0]) @ inv[:3, :3].T + inv[:3, 3]
    pose = base.object_pose.copy()
    pose[:, :3] = pose[:, :3] @ inv[:3, :3].T + inv[:3, 3]
    from scipy.spatial.transform import Rotation

    pose[:, 3:] = (Rotation.from_matrix(inv[:3, :3]) * Rotation.from_quat(pose[:, 3:], scalar_first=True)).as_quat(
        scalar_first=True)
    return Sequence(name="chiral", fps=30.0, object=ObjectSpec(name="chiral", mass_kg=0.1, mesh_vertices=verts,
                    mesh_faces=faces), object_pose=pose, hands=[HandTrack("right", base.hands[0].valid, kp)],
                    world_from_source=world).validate()


def _signed_volume(obj: ObjectSpec) -> float:
    """The mesh's signed volume: positive where its faces wind outward."""
    assert obj.mesh_vertices is not None and obj.mesh_faces is not None
    v = obj.mesh_vertices[obj.mesh_faces]
    return float(np.einsum("fi,fi->f", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6)


def _world_surface(seq: Sequence, frame: int) -> np.ndarray:
    pose = seq.object_pose_world()[frame]
    return np.asarray(seq.object.surface_vertices() @ quat_to_matrix(pose[3:]).T + pose[:3])


def test_mirror_reflects_hand_and_object_surface_and_swaps_the_side() -> None:
    seq = _mesh_sequence()
    mir = mirror_sequence(seq)
    assert mir.hands[0].side == "left" and mir.name.endswith("__mirrored")
    np.testing.assert_allclose(mir.keypoints_world(mir.hands[0]), seq.keypoints_world(seq.hands[0]) @ M.T, atol=1e-12)
    for frame in (0, seq.num_frames - 1):
        np.testing.assert_allclose(_world_surface(mir, frame), _world_surface(seq, frame) @ M.T, atol=1e-12)
    # Faces are re-wound: the signed volume (outward normals) keeps its sign under the reflection.
    assert np.sign(_signed_volume(mir.object)) == np.sign(_signed_volume(seq.object)) != 0
    back = mirror_sequence(mir)
    assert back.hands[0].side == "right"
    np.testing.assert_allclose(back.object_pose_world(), seq.object_pose_world(), atol=1e-12)


def test_mirror_keeps_a_primitive_and_rejects_a_tilted_plane() -> None:
    seq = short_example_sequence()
    assert mirror_object(seq.object).primitive == "box"
    with pytest.raises(ValueError, match="vertical"):
        mirror_sequence(seq, normal=(1.0, 0.0, 1.0))
    other = mirror_sequence(seq, normal=(1.0, 1.0, 0.0))  # any vertical plane
    np.testing.assert_allclose(other.object_pose_world()[:, 2], seq.object_pose_world()[:, 2], atol=1e-12)


def test_left_palm_box_mirrors_the_right_one() -> None:
    def palm(side: Side) -> tuple[list[float], list[float]]:
        xml = hand_worldbody_xml(default_geometry(side), SimConfig(), np.zeros(3), np.array([1.0, 0, 0, 0]))
        found = re.search(rf'<geom name="{side}_palm"[^>]*size="([^"]*)" pos="([^"]*)"', xml)
        assert found is not None
        size, pos = found.groups()
        return [float(v) for v in size.split()], [float(v) for v in pos.split()]

    (size_r, pos_r), (size_l, pos_l) = palm("right"), palm("left")
    assert size_l == size_r
    np.testing.assert_allclose(pos_l, np.array(pos_r) * [1, -1, 1])


def test_mirror_signs_negate_abduction_and_twist_only_whose_limits_are_symmetric() -> None:
    assert all((s < 0) == name.endswith(("_abd", "_twist")) for s, name in zip(MIRROR_SIGNS, HINGE_NAMES, strict=True))
    # The left hand shares the right hand's limits, so a mirrored pose must stay within them.
    np.testing.assert_array_equal(np.sort(JOINT_LIMITS * MIRROR_SIGNS[:, None], axis=1), JOINT_LIMITS)


def test_retargeting_and_controls_of_the_mirror_are_the_mirror_image() -> None:
    """Same keyframes in both control spaces -> hinge targets x MIRROR_SIGNS, wrist positions and rotations
    reflected: the optimiser faces the same problem for a sequence and its mirror."""
    from common.job_options import JobOptions
    from worker.refine.prepare import prepare

    seq = short_example_sequence()
    mir = mirror_sequence(seq)
    options = JobOptions(free_wrist_translation=True)
    a, b = prepare(seq, options), prepare(mir, options)
    ra, rb = a.references[0], b.references[0]
    np.testing.assert_allclose(rb.geometry.bases, ra.geometry.bases * [1, -1, 1], atol=1e-12)
    np.testing.assert_allclose(rb.q, ra.q * MIRROR_SIGNS, atol=1e-9)
    sa, sb = a.spaces["right"], b.spaces["left"]
    assert not sa.mirrored and sb.mirrored
    keyframes = np.random.default_rng(0).normal(0.0, 1.0, (sa.n_keyframes, sa.dim))
    qa, pa, ra_q = sa.frame_controls(keyframes)
    qb, pb, rb_q = sb.frame_controls(keyframes)
    np.testing.assert_allclose(qb, qa * MIRROR_SIGNS, atol=1e-9)
    np.testing.assert_allclose(pb, pa @ M.T, atol=1e-9)
    # Wrist frames: the left hand's frame is M R S with S = diag(1, -1, 1) (hand_model's mirror convention).
    np.testing.assert_allclose(quat_to_matrix(rb_q), M @ quat_to_matrix(ra_q) @ np.diag([1.0, -1.0, 1.0]), atol=1e-9)
    # The old convention (results made before issue #15) did not mirror: the same keyframes differ.
    old = prepare(mir, options, mirror_left=False).spaces["left"]
    assert not np.allclose(old.frame_controls(keyframes)[0], qa * MIRROR_SIGNS, atol=1e-3)


def _same_points(a: np.ndarray, b: np.ndarray) -> None:
    """The same point sets (a primitive's tessellation is symmetric under the reflection, but not point by point)."""
    from scipy.spatial.distance import cdist

    d = cdist(a, b)
    assert a.shape == b.shape and d.min(axis=0).max() < 1e-12 and d.min(axis=1).max() < 1e-12


def _part_surfaces(seq: Sequence, frame: int) -> list[np.ndarray]:
    """Every part's surface in the world at ``frame`` (forward kinematics from the world base pose)."""
    assert seq.articulation is not None
    poses = seq.object.part_poses(seq.object_pose_world()[frame], seq.articulation[frame])
    return [shape.surface_vertices() @ quat_to_matrix(poses[k, 3:]).T + poses[k, :3]
            for k, shape in enumerate(seq.object.part_shapes())]  # fmt: skip


@pytest.mark.parametrize("normal", [(1.0, 0.0, 0.0), (0.6, -0.8, 0.0)])
def test_an_articulated_object_mirrors_part_by_part(normal: tuple[float, float, float]) -> None:
    """Each part is the reflection of the original's at every frame: a tilted revolute door (a pseudo-vector axis),
    a prismatic drawer (a plain direction), a chiral mesh knob hung from the drawer, in a tilted source frame."""
    from tests.support.articulated import drawer_cabinet_sequence

    seq = drawer_cabinet_sequence(frames=6, parts=4)
    world = np.eye(4)
    world[:3, :3] = quat_to_matrix(np.array([0.96, 0.1, -0.2, 0.15]) / np.linalg.norm([0.96, 0.1, -0.2, 0.15]))
    world[:3, 3] = [0.1, -0.2, 0.3]
    seq.world_from_source = world
    seq.object_pose = seq.object_pose.copy()
    seq.object_pose[:, 3:] = np.array([0.9, 0.1, 0.3, -0.2]) / np.linalg.norm([0.9, 0.1, 0.3, -0.2])
    seq = seq.validate()
    m = reflection(normal)
    mir = mirror_sequence(seq, normal=normal)
    np.testing.assert_array_equal(mir.articulation, seq.articulation)
    assert mir.object.part_names == seq.object.part_names
    assert [j.limits.tolist() for j in mir.object.joints] == [j.limits.tolist() for j in seq.object.joints]
    for frame in range(seq.num_frames):
        for original, mirrored in zip(_part_surfaces(seq, frame), _part_surfaces(mir, frame), strict=True):
            _same_points(mirrored, original @ m.T)
    # Mirroring twice gives every part back.
    back = mirror_sequence(mir, normal=normal)
    for frame in (0, seq.num_frames - 1):
        for original, twice in zip(_part_surfaces(seq, frame), _part_surfaces(back, frame), strict=True):
            _same_points(twice, original)
    # Re-winding keeps every mesh part's outward normals.
    knob, knob_m = seq.object.parts[2].shape, mir.object.parts[2].shape
    assert np.sign(_signed_volume(knob)) == np.sign(_signed_volume(knob_m)) != 0
