"""Raw replay end to end on the built-in example (clean observation): trajectory, contacts, metrics, result file."""

from __future__ import annotations

import numpy as np
import pytest

from common.result_format import CONTACT_KEYS, read_arrays, read_contacts, read_summary
from worker.example.sequences import example_sequence
from worker.simulation.replay import ReplayResult, raw_replay, replay_result_bytes


@pytest.fixture(scope="module")
def replay() -> ReplayResult:
    return raw_replay(example_sequence(errors=False))


def test_replay_records_every_frame(replay: ReplayResult) -> None:
    rec = replay.record
    assert rec.object_pose.shape == (72, 7) and rec.object_vel.shape == (72, 6)
    assert rec.keypoints["right"].shape == (72, 21, 3)
    assert replay.steps == 24 + 71 * 8  # settle (0.1 s) + 8 substeps per frame
    # Frame 0: the object rests where the data put it (on the table), the hand at its frame-0 pose.
    np.testing.assert_allclose(rec.object_pose[0, :3], replay.object_pose_ref[0, :3], atol=2e-3)
    assert np.linalg.norm(rec.keypoints["right"][0] - replay.references[0].fitted_keypoints()[0], axis=1).max() < 3e-3
    for key in ("E_t", "E_r", "E_j", "E_ft"):
        assert np.isfinite(replay.metrics[key])
    assert replay.metrics["E_j"] < 3.0  # the hand follows its reference (cm)


def test_contacts_are_physical(replay: ReplayResult) -> None:
    c = replay.contacts
    n = len(c["contact_frame"])
    assert n > 5
    assert set(c["contact_frame"]) & set(range(34, 42))  # the fingers touch the box once the hand has closed
    assert set(c["contact_hand"]) == {"right"} and all(b.startswith("right_") for b in c["contact_body"])
    np.testing.assert_allclose(np.linalg.norm(c["contact_normal"], axis=1), 1.0, atol=1e-9)
    assert np.all(c["contact_depth"] >= 0) and np.all(c["contact_depth"] < 0.02)
    # The hand pushes the object: the force on the object points against the object->hand normal.
    assert np.all(np.sum(c["contact_force"] * c["contact_normal"], axis=1) <= 1e-9)
    # Object-local points are the world points seen from the object's pose at that frame (within 1 substep).
    pose = replay.record.object_pose[c["contact_frame"]]
    assert np.all(np.linalg.norm(c["contact_pos_object"], axis=1) < 0.2)
    assert np.all(np.linalg.norm(c["contact_pos_world"] - pose[:, :3], axis=1) < 0.2)


def test_result_file_round_trip(replay: ReplayResult) -> None:
    blob = replay_result_bytes(replay)
    summary = read_summary(blob)
    assert summary["metrics"]["raw"]["E_t"] == pytest.approx(replay.metrics["E_t"])
    assert summary["simulated_steps"] == replay.steps and summary["config"]["timestep"] == pytest.approx(1 / 240)
    assert summary["versions"]["mujoco"] and "right" in summary["ik_residual_mm"]
    arrays = read_arrays(blob)
    assert all(k in arrays for k in CONTACT_KEYS)
    assert arrays["right_q_target"].shape == (72, 45) and arrays["object_pose_sim"].shape == (72, 7)
    rows = read_contacts(blob, start=36, end=40)
    assert rows and all(36 <= r["frame"] < 40 for r in rows)
