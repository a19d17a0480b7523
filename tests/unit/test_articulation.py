"""Articulated objects (issue #52): forward kinematics, the joint checks, E_a and its success limit, the
articulation loss term, the joint-hands stacking and the window loop's levels for two hands."""

from __future__ import annotations

import numpy as np
import pytest

from common.articulation import ObjectJoint, joint_transform, part_poses
from common.errors import SequenceValidationError
from common.geometry import quat_rotate
from common.job_options import JobOptions
from worker.example.hinged_box import hinged_box_object, short_hinged_box_sequence
from worker.refine.losses import articulation_term
from worker.refine.run import cma_settings
from worker.simulation.metrics import SUCCESS_ARTICULATION, ArticulationFrames, compute_metrics

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def hinge(kind: str = "revolute", axis: tuple[float, float, float] = (0.0, 0.0, 1.0),
          origin: tuple[float, float, float] = (0.1, 0.0, 0.0), parent: str = "base") -> ObjectJoint:
    return ObjectJoint("j", kind, parent, np.array(axis), np.array(origin), IDENTITY.copy(), np.array([-2.0, 2.0]))  # type: ignore[arg-type]


def test_a_revolute_joint_turns_its_part_about_the_axis_through_the_part_origin() -> None:
    pos, quat = joint_transform(hinge(), np.array([np.pi / 2]))
    assert np.allclose(pos, [[0.1, 0.0, 0.0]])  # the origin stays where the joint is
    # A point 5 cm along the part's x axis turns a quarter about z: it ends 5 cm along y.
    assert np.allclose(quat_rotate(quat, np.array([0.05, 0.0, 0.0])), [[0.0, 0.05, 0.0]], atol=1e-12)


def test_a_prismatic_joint_slides_its_part_along_the_axis_in_the_parent_frame() -> None:
    joint = hinge("prismatic", axis=(1.0, 0.0, 0.0))
    joint.origin_quat = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # part frame turned 90 deg
    pos, quat = joint_transform(joint, np.array([0.03]))
    assert np.allclose(pos, [[0.1, 0.03, 0.0]])  # the part's x axis is the parent's y axis
    assert np.allclose(quat, joint.origin_quat)


def test_part_poses_chain_through_their_parents_and_follow_the_base() -> None:
    first, second = hinge(), hinge(origin=(0.05, 0.0, 0.0), parent="a")
    base = np.array([[1.0, 2.0, 3.0, *IDENTITY]])
    poses = part_poses(base, [first, second], [0, 1], np.array([[np.pi / 2, np.pi / 2]]))
    assert np.allclose(poses[0, 0], base[0])
    assert np.allclose(poses[0, 1, :3], [1.1, 2.0, 3.0])
    # The second part hangs 5 cm along the first part's x axis, which points along world y after its turn.
    assert np.allclose(poses[0, 2, :3], [1.1, 2.05, 3.0])
    assert np.allclose(quat_rotate(poses[0, 2, 3:], np.array([1.0, 0.0, 0.0])), [-1.0, 0.0, 0.0], atol=1e-12)


def bad(field_edit: str) -> str:
    seq = short_hinged_box_sequence(errors=False)
    joint = seq.object.parts[0].joint
    if field_edit == "axis":
        joint.axis = np.zeros(3)
    elif field_edit == "value":
        assert seq.articulation is not None
        seq.articulation = seq.articulation.copy()
        seq.articulation[3, 0] = 2.5
    elif field_edit == "parent":
        joint.parent = "lid"
    elif field_edit == "mesh":
        seq.object.parts[0].shape.mesh_vertices = None
        seq.object.parts[0].shape.mesh_faces = None
    elif field_edit == "shape":
        seq.articulation = np.zeros((seq.num_frames, 2))
    with pytest.raises(SequenceValidationError) as err:
        seq.validate()
    return str(err.value)


@pytest.mark.parametrize(("edit", "field"), [
    ("axis", "object.parts[0].joint.axis"), ("value", "articulation"), ("parent", "object.parts[0].joint.parent"),
    ("mesh", "object.parts[0]"), ("shape", "articulation"),
])  # fmt: skip
def test_bad_articulated_objects_are_refused_naming_the_field(edit: str, field: str) -> None:
    assert field in bad(edit)


def test_e_a_is_the_largest_joint_error_per_frame_and_success_needs_it_within_the_limit() -> None:
    n = 12
    pose = np.tile([0.0, 0.0, 0.1, *IDENTITY], (n, 1))
    ref = np.zeros((n, 2))
    sim = ref.copy()
    sim[:, 0] = np.radians(10.0)  # revolute: 10 deg
    sim[:, 1] = 0.02  # prismatic: 2 cm
    m = compute_metrics(pose, pose, {}, {}, {}, articulation=ArticulationFrames(sim, ref, ("revolute", "prismatic")))
    assert m["E_a"] == pytest.approx(10.0) and m["success"]
    sim[11, 1] = 0.01 * SUCCESS_ARTICULATION["prismatic"] + 0.001  # one frame past 3 cm
    m = compute_metrics(pose, pose, {}, {}, {}, articulation=ArticulationFrames(sim, ref, ("revolute", "prismatic")))
    assert not m["success"] and not m["paper"]["success"]
    assert m["max_E_a"] == pytest.approx(10.0)  # the largest error is still the 10 deg of the first joint


def test_rigid_metrics_carry_no_articulation_figures() -> None:
    pose = np.tile([0.0, 0.0, 0.1, *IDENTITY], (3, 1))
    m = compute_metrics(pose, pose, {}, {}, {})
    assert "E_a" not in m and "e_a" not in m["per_frame"]


def test_the_articulation_term_grows_quadratically_past_its_margin() -> None:
    ref = np.zeros((4, 1))
    small = articulation_term(np.full((1, 4, 1), np.radians(5.0)), ref, ("revolute",))
    large = articulation_term(np.full((1, 4, 1), np.radians(20.0)), ref, ("revolute",))
    assert small[0] == pytest.approx(4 * np.radians(5.0) / 0.04)  # linear within the 10 deg margin
    assert large[0] > 4 * np.radians(20.0) / 0.04 + 4 * 15.0  # plus ((20 - 10) / 2.5)^2 = 16 per frame


def test_one_hand_window_levels_are_as_before_and_two_hands_scale_them() -> None:
    one = cma_settings(JobOptions(), 5)
    assert one.skip_loss == 0.3 * 3 * 5 and one.escalate_loss == 2.5 * 3 * 5  # the same floats as before
    two = cma_settings(JobOptions(), 5, hands=2)
    joint = cma_settings(JobOptions(two_hands="joint"), 5, hands=2)
    assert two.escalate_loss == pytest.approx(2 * one.escalate_loss)
    assert joint.escalate_loss == pytest.approx(1.5 * one.escalate_loss)


def test_the_hinged_box_example_is_a_valid_articulated_sequence() -> None:
    seq = short_hinged_box_sequence()
    assert seq.object.part_names == ["base", "lid"] and [h.side for h in seq.hands] == ["right", "left"]
    assert seq.articulation is not None and seq.articulation.max() > 0.5
    obj = hinged_box_object()
    poses = obj.part_poses(np.array([0.0, 0.0, 0.045, *IDENTITY]), np.array([0.0]))
    # At 0 the lid's frame sits on the base's top face, on the hinge line at its back edge.
    assert np.allclose(poses[1, :3], [0.05, -0.028, 0.09])
