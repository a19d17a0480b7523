"""bench/arctic_recordings.py's motion figures on sequences the test builds (no ARCTIC data needed)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.arctic_recordings import BLOCK, Motion, turn_bins
from common.sequence import Sequence
from worker.example.hinged_box import hinged_box_sequence

ROOT = Path(__file__).resolve().parents[2]


def _turning(seq: Sequence, deg_per_frame: float, fps: float) -> Sequence:
    """``seq`` with its object turning about z at ``deg_per_frame`` from its first pose, at ``fps``."""
    pose = np.array(seq.object_pose, dtype=np.float64)
    half = np.radians(deg_per_frame) * np.arange(len(pose)) / 2.0
    pose[:, 3:] = np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], axis=1)
    return dataclasses.replace(seq, object_pose=pose, fps=fps)


def test_a_steady_turn_is_counted_in_every_frame_and_scaled_to_30_fps() -> None:
    seq = _turning(hinged_box_sequence(), 6.0, 30.0)
    m = Motion.of(seq)
    assert m.turn_deg.shape == (seq.num_frames - 1,)
    assert np.allclose(m.turn_deg, 6.0, atol=1e-6)
    assert m.frames_over(5.0) == seq.num_frames - 1 and m.frames_over(10.0) == 0
    assert m.sustained_turn() == pytest.approx(6.0)
    # The same motion recorded at 60 fps turns half as far per frame, which is 6 deg per frame at 30 fps again.
    fast = Motion.of(_turning(hinged_box_sequence(), 3.0, 60.0))
    assert np.allclose(fast.turn_deg, 6.0, atol=1e-6)


def test_the_hinge_is_reported_in_degrees_and_a_short_burst_does_not_count_as_sustained() -> None:
    seq = hinged_box_sequence()
    assert seq.num_frames > BLOCK
    m = Motion.of(seq)
    assert m.hinge_deg is not None and m.hinge_deg.shape == (seq.num_frames, 1)
    assert seq.articulation is not None and np.allclose(m.hinge_deg, np.degrees(seq.articulation))
    pose = np.array(seq.object_pose, dtype=np.float64)
    pose[:, 3:] = [1.0, 0.0, 0.0, 0.0]
    pose[5:, 3:] = [np.cos(np.radians(20.0)), 0.0, 0.0, np.sin(np.radians(20.0))]  # one 40-degree step
    burst = Motion.of(dataclasses.replace(seq, object_pose=pose))
    assert burst.frames_over(10.0) == 1 and burst.turn_deg.max() == pytest.approx(40.0)
    assert burst.sustained_turn() == pytest.approx(40.0 / BLOCK)


def test_a_folder_without_sequences_is_a_usage_error(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "arctic_recordings.py"), "--arctic", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert out.returncode == 2 and "no usable sequence" in out.stderr


def test_without_an_archive_the_dexycb_bins_are_left_out(tmp_path: Path) -> None:
    assert turn_bins(tmp_path / "missing.jsonl") == []
