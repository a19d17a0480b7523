"""The object-excursion loss: free within 2 cm / 20 deg, quadratic beyond (worker.refine.losses)."""

from __future__ import annotations

import numpy as np
import pytest

from worker.refine.losses import ObjectTargets, WindowRecord, object_terms


def _record(offsets_m: list[float], angles_deg: list[float]) -> tuple[WindowRecord, ObjectTargets]:
    f = len(offsets_m)
    half = np.radians(angles_deg) / 2
    rec = WindowRecord(
        frames=np.arange(f),
        obj_pos=np.column_stack([offsets_m, np.zeros(f), np.zeros(f)])[None],
        obj_quat=np.column_stack([np.cos(half), np.zeros(f), np.zeros(f), np.sin(half)])[None],
        obj_vel=np.zeros((1, f, 6)),
        keypoints={},
        hinge_vel={},
        offsets={},
    )
    ref = ObjectTargets(pos=np.zeros((f, 3)), quat=np.tile([1.0, 0, 0, 0], (f, 1)), vel=np.zeros((f, 6)))
    return rec, ref


def test_excursion_is_free_inside_the_margin_and_quadratic_beyond() -> None:
    inside = object_terms(*_record([0.0, 0.019, 0.01], [0.0, 19.0, 10.0]))
    assert inside["object_excursion"][0] == 0.0
    assert inside["object_pose"][0] > 0  # the ordinary pose term still counts these frames
    one_frame = object_terms(*_record([0.0, 0.03, 0.0], [0.0, 0.0, 30.0]))
    # 3 cm: ((3 - 2) / 0.5)^2 = 4; 30 deg: ((30 - 20) / 5)^2 = 4.
    assert one_frame["object_excursion"][0] == pytest.approx(8.0)


def test_a_rotation_weight_discounts_only_the_rotation_part_of_the_pose_term() -> None:
    # A window's lookahead frames (``SimWindowProblem``) weigh the object's rotation error by
    # ``rotation_weight``; its position error and the excursion beyond 20 deg still count there in full.
    rec, ref = _record([0.0, 0.01, 0.0], [0.0, 0.0, 30.0])
    full = object_terms(rec, ref)
    rec.rotation_weight = np.array([1.0, 0.0, 0.0])
    discounted = object_terms(rec, ref)
    # 1 cm on frame 1 costs (1 - eta) * 1 = 0.5 either way; 30 deg on frame 2 costs eta * 0.524 / 0.04 in full.
    assert full["object_pose"][0] == pytest.approx(0.5 + 0.5 * np.radians(30.0) / 0.04)
    assert discounted["object_pose"][0] == pytest.approx(0.5)
    assert discounted["object_excursion"][0] == full["object_excursion"][0] == pytest.approx(4.0)
    rec.rotation_weight = np.array([1.0, 1.0, 0.5])
    assert object_terms(rec, ref)["object_pose"][0] == pytest.approx(0.5 + 0.25 * np.radians(30.0) / 0.04)
