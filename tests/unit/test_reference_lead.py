"""bench/reference_lead.py: when the recorded object moves against when the recorded hand first touches it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.reference_lead import PAPER_FIRST_FRAME, read_errors, reference_lead
from common.sequence import HandTrack, ObjectSpec, Sequence

RADIUS = 0.05


def _sphere_points(n: int = 2000) -> np.ndarray:
    """Fibonacci points on a sphere of RADIUS: a dense mesh-like surface."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    r = np.sqrt(1 - z**2)
    return RADIUS * np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _sequence(frames: int, rises_after: int, gap_cm: np.ndarray, valid: np.ndarray | None = None) -> Sequence:
    """A ball resting until ``rises_after``, then rising 1 cm a frame; the index fingertip (keypoint 8) is
    ``gap_cm`` from its surface along world x, every other keypoint half a metre away."""
    t = np.arange(frames)
    pos = np.zeros((frames, 3))
    pos[:, 2] = 0.01 * np.clip(t - rises_after, 0, None)
    quat = np.tile([np.cos(0.4), 0.0, 0.0, np.sin(0.4)], (frames, 1))  # turned about z: the test uses its frame
    keypoints = np.tile(pos[:, None] + np.array([0.5, 0.5, 0.5]), (1, 21, 1))
    keypoints[:, 8] = pos + np.stack([RADIUS + gap_cm / 100, np.zeros(frames), np.zeros(frames)], axis=1)
    obj = ObjectSpec("ball", 0.1, mesh_vertices=_sphere_points())
    hand = HandTrack("right", np.ones(frames, bool) if valid is None else valid, keypoints=keypoints)
    return Sequence("lead", 30.0, obj, np.concatenate([pos, quat], axis=1), [hand])


def test_an_object_moving_before_the_hand_arrives_is_a_lead_and_its_frames_a_floor() -> None:
    gap = np.clip(19.8 - np.arange(40), 0.5, None)  # cm: within 1 cm from frame 19 on
    lead = reference_lead(_sequence(40, rises_after=15, gap_cm=gap))
    assert lead.moved == 16  # 1 cm up: past the 5 mm rule
    assert lead.touch == 19
    assert lead.lead_frames == 3
    # Frames 16, 17, 18 are 1, 2, 3 cm up while untouched, over the paper's 30 frames; no turn.
    assert lead.floor_t_cm == pytest.approx(6.0 / (40 - PAPER_FIRST_FRAME))
    assert lead.ahead_t_cm == pytest.approx(lead.floor_t_cm)
    assert lead.floor_r_deg == pytest.approx(0.0, abs=1e-6)


def test_a_hand_that_touches_first_has_no_lead_and_an_invalid_frame_is_no_touch() -> None:
    gap = np.clip(19.8 - np.arange(40), 0.5, None)
    early = reference_lead(_sequence(40, rises_after=25, gap_cm=gap))
    assert early.lead_frames == 19 - 26 and early.floor_t_cm == pytest.approx(0.0)
    valid = np.ones(40, bool)
    valid[19:22] = False  # the hand is not annotated when it arrives
    late = reference_lead(_sequence(40, rises_after=15, gap_cm=gap, valid=valid))
    assert late.touch == 22
    never = reference_lead(_sequence(40, rises_after=15, gap_cm=np.full(40, 5.0)))
    assert never.touch is None and never.lead_frames is None
    # Untouched to the end: every paper's frame from 16 on counts (1 .. 24 cm).
    assert never.floor_t_cm == pytest.approx(sum(range(1, 25)) / 30)


def test_errors_come_from_the_refine_reports_table(tmp_path: Path) -> None:
    report = tmp_path / "refine.md"
    report.write_text(
        "# Refinement\n\n| sequence | object | refined ok (1st) | E_t 10+ | E_r 10+ |\n|---|---|---|---|---|\n"
        "| a | mug | yes (no) | 0.5 | 2.1 |\n| b | can | no (no) | 9.0 | 40.0 |\n\nafter the table\n"
    )
    assert read_errors(report) == {"a": (True, 0.5, 2.1), "b": (False, 9.0, 40.0)}
    (tmp_path / "other.md").write_text("# no table here\n")
    with pytest.raises(SystemExit, match="no per-sequence table"):
        read_errors(tmp_path / "other.md")
