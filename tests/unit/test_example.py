"""The built-in example: valid, deterministic, physically consistent, with vision-like errors."""

from __future__ import annotations

import numpy as np

from common.geometry import quat_to_matrix
from worker.example.sequences import example_sequence, short_example_sequence


def test_example_is_valid_and_deterministic() -> None:
    a, b = example_sequence(), example_sequence()
    assert a.num_frames == 72 and a.fps == 30.0 and a.object.primitive == "box"
    assert 0.1 <= a.object.mass_kg <= 0.4
    np.testing.assert_array_equal(np.asarray(a.hands[0].keypoints), np.asarray(b.hands[0].keypoints))
    assert short_example_sequence().num_frames == 24


def test_object_rests_then_is_lifted_about_20_cm() -> None:
    seq = example_sequence(errors=False)
    pose = seq.object_pose_world()
    z = pose[:, 2]
    assert np.allclose(z[:38], z[0])  # at rest until the hand has closed
    assert 0.19 <= z.max() - z[0] <= 0.21
    bottom = (seq.object.surface_vertices() @ quat_to_matrix(pose[0, 3:]).T + pose[0, :3])[:, 2].min()
    assert abs(bottom) < 1e-9  # standing on the table
    # Once lifted, the object moves rigidly with the wrist.
    kp = seq.hands[0].keypoints
    assert kp is not None
    wrist = kp[:, 0]
    np.testing.assert_allclose(np.diff(z[40:]), np.diff(wrist[40:, 2]), atol=1e-9)


def test_observation_has_vision_like_errors() -> None:
    clean, noisy = example_sequence(errors=False), example_sequence(errors=True)
    kp_noisy, kp_clean = noisy.hands[0].keypoints, clean.hands[0].keypoints
    assert kp_noisy is not None and kp_clean is not None
    diff = np.linalg.norm(kp_noisy - kp_clean, axis=2)  # (T,21) metres
    assert 0.001 < np.median(diff) < 0.02  # jitter + offsets of millimetres, not centimetres
    tips = diff[-10:, [8, 12, 16, 20]]
    assert tips.max() > 0.005  # finger errors (hover / penetration) at the grasp
    assert not np.allclose(noisy.object_pose[:, :3], clean.object_pose[:, :3])  # object pose jitter
