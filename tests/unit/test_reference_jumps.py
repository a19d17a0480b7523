"""bench/reference_jumps.py: finding the recorded object's largest frame-to-frame turn, and reading outcomes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.reference_jumps import frame_rotation_steps, largest_jump, read_outcomes
from common.geometry import quat_exp, quat_mul


def _box(extents: tuple[float, float, float]) -> np.ndarray:
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    return corners * np.asarray(extents) / 2


def _track(steps_deg: list[float], axis: np.ndarray) -> np.ndarray:
    """A pose track turning by each step about ``axis`` (object frame) and rising 1 cm a frame."""
    quats = [np.array([1.0, 0.0, 0.0, 0.0])]
    for step in steps_deg:
        quats.append(quat_mul(quats[-1], quat_exp(np.radians(step) * axis)))
    pos = np.stack([np.zeros(len(quats)), np.zeros(len(quats)), 0.01 * np.arange(len(quats))], axis=1)
    return np.concatenate([pos, np.stack(quats)], axis=1)


def test_a_smooth_turn_has_small_steps_about_its_axis() -> None:
    axis = np.array([0.0, 0.6, 0.8])
    pose = _track([3.0] * 20, axis)
    angle, axes = frame_rotation_steps(pose[:, 3:])
    np.testing.assert_allclose(angle, 3.0, atol=1e-9)
    np.testing.assert_allclose(axes, np.broadcast_to(axis, axes.shape), atol=1e-9)


def test_a_spin_about_a_markers_long_axis_is_found_where_it_happens() -> None:
    steps = [2.0] * 30
    steps[12] = 95.0  # one frame: the pose fit flips about the marker's symmetry axis
    marker = _box((0.02, 0.019, 0.12))  # long along z
    jump = largest_jump(_track(steps, np.array([0.0, 0.0, 1.0])), marker)
    assert jump.rotation_deg == pytest.approx(95.0)
    assert jump.frame == 12
    assert jump.axis == "long" and jump.axis_cos == pytest.approx(1.0)
    assert jump.translation_cm == pytest.approx(1.0)


def test_a_tilt_of_a_flat_box_is_about_another_axis() -> None:
    steps = [1.0] * 10
    steps[4] = 40.0
    jump = largest_jump(_track(steps, np.array([1.0, 0.0, 0.0])), _box((0.10, 0.06, 0.02)))  # long along x
    assert jump.axis == "long" and jump.frame == 4
    jump = largest_jump(_track(steps, np.array([0.0, 0.0, 1.0])), _box((0.10, 0.06, 0.02)))
    assert jump.axis == "short"


def test_a_quaternion_sign_flip_is_no_jump() -> None:
    pose = _track([2.0] * 10, np.array([0.0, 0.0, 1.0]))
    pose[5, 3:] *= -1  # the same rotation written the other way
    assert largest_jump(pose, _box((0.1, 0.05, 0.02))).rotation_deg == pytest.approx(2.0)


def test_outcomes_come_from_the_refine_reports_table(tmp_path: Path) -> None:
    report = tmp_path / "refine.md"
    report.write_text(
        "# Refinement\n\n| sequence | object | refined ok (1st) | E_t |\n|---|---|---|---|\n"
        "| a | mug | yes (no) | 0.5 |\n| b | can | no (no) | 9.0 |\n\nafter the table\n"
    )
    assert read_outcomes(report) == {"a": True, "b": False}
    (tmp_path / "other.md").write_text("# no table here\n")
    with pytest.raises(SystemExit, match="no per-sequence table"):
        read_outcomes(tmp_path / "other.md")
