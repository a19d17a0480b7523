"""A sequence at a multiple of its frame rate (issue #52 item 6): the recorded frames are kept, the new ones lie
between them, rotations by slerp."""

from __future__ import annotations

import numpy as np
import pytest

from common.geometry import rotation_error_deg
from common.sequence_resample import resample_sequence
from worker.example import short_example_sequence
from worker.example.hinged_box import short_hinged_box_sequence


def test_doubling_keeps_the_recorded_frames_and_puts_new_ones_between() -> None:
    seq = short_example_sequence()
    fast = resample_sequence(seq, 2)
    assert fast.fps == 2 * seq.fps and fast.num_frames == 2 * seq.num_frames - 1
    assert np.allclose(fast.object_pose[::2], seq.object_pose, atol=1e-12)
    hand, fast_hand = seq.hands[0], fast.hands[0]
    assert fast_hand.keypoints is not None and hand.keypoints is not None
    assert np.allclose(fast_hand.keypoints[1::2], (hand.keypoints[:-1] + hand.keypoints[1:]) / 2)
    # A new frame's rotation is half way: equally far from both neighbours.
    q = fast.object_pose[:, 3:]
    assert np.allclose(rotation_error_deg(q[1:-1:2], q[:-2:2]), rotation_error_deg(q[1:-1:2], q[2::2]), atol=1e-9)


def test_joint_values_and_validity_follow() -> None:
    seq = short_hinged_box_sequence()
    seq.hands[1].valid[4] = False
    fast = resample_sequence(seq, 3)
    assert seq.articulation is not None and fast.articulation is not None
    assert np.allclose(fast.articulation[::3], seq.articulation)
    valid = fast.hands[1].valid
    assert not valid[12] and not valid[11] and not valid[13] and valid[9] and valid[15]


def test_a_bad_factor_is_refused() -> None:
    with pytest.raises(ValueError, match="factor"):
        resample_sequence(short_example_sequence(), 0)
