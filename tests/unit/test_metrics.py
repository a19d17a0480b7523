"""DESIGN §1.8 metrics on hand-made trajectories with known errors."""

from __future__ import annotations

import numpy as np
import pytest

from common.geometry import rotation_error_deg
from worker.simulation.metrics import compute_metrics, scalar_metrics


def _poses(n: int) -> np.ndarray:
    poses = np.zeros((n, 7))
    poses[:, 3] = 1.0
    poses[:, 2] = np.linspace(0.0, 0.2, n)
    return poses


def _hands(n: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    kp = np.random.default_rng(0).normal(size=(n, 21, 3))
    return {"right": kp}, {"right": np.ones(n, dtype=bool)}


def test_identical_trajectories_have_zero_error() -> None:
    ref = _poses(10)
    kp, valid = _hands(10)
    m = compute_metrics(ref, ref.copy(), kp, kp, valid)
    assert m["E_t"] == 0 and m["E_r"] == pytest.approx(0, abs=1e-5) and m["E_j"] == 0 and m["E_ft"] == 0
    assert m["success"] is True


def test_known_offsets() -> None:
    ref = _poses(10)
    sim = ref.copy()
    sim[:, 0] += 0.02  # 2 cm everywhere
    half = np.deg2rad(45.0) / 2
    sim[5:, 3:] = [np.cos(half), 0.0, 0.0, np.sin(half)]  # 45 deg about z on half the frames
    kp, valid = _hands(10)
    kp_sim = {"right": kp["right"].copy()}
    kp_sim["right"][:, 4] += [0.0, 0.05, 0.0]  # thumb tip 5 cm off
    valid["right"][:2] = False
    kp_sim["right"][:2] += 10.0  # invalid frames do not count
    m = compute_metrics(sim, ref, kp_sim, kp, valid)
    assert m["E_t"] == pytest.approx(2.0)
    assert m["E_r"] == pytest.approx(22.5, abs=1e-6)
    assert m["max_E_r"] == pytest.approx(45.0, abs=1e-6)
    assert m["E_j"] == pytest.approx(5.0 / 21)
    assert m["E_ft"] == pytest.approx(1.0)
    assert m["success"] is False  # 45 deg > 30 deg
    assert np.isnan(m["per_frame"]["e_j_cm"][0]) and m["per_frame"]["e_t_cm"].shape == (10,)
    assert "per_frame" not in scalar_metrics(m)


def test_position_threshold_decides_success() -> None:
    ref = _poses(5)
    kp, valid = _hands(5)
    sim = ref.copy()
    sim[3, 1] += 0.0299
    assert compute_metrics(sim, ref, kp, kp, valid)["success"] is True
    sim[3, 1] += 0.0002
    assert compute_metrics(sim, ref, kp, kp, valid)["success"] is False


def test_rotation_error_ignores_quaternion_sign() -> None:
    q = np.array([0.5, 0.5, 0.5, 0.5])
    assert rotation_error_deg(q, -q) == pytest.approx(0.0, abs=1e-5)


def test_shape_errors_name_the_argument() -> None:
    kp, valid = _hands(4)
    with pytest.raises(ValueError, match="object_pose_sim"):
        compute_metrics(_poses(4), _poses(5), kp, kp, valid)
    with pytest.raises(ValueError, match="keypoints_sim"):
        compute_metrics(_poses(5), _poses(5), kp, kp, valid)


def test_the_papers_protocol_leaves_out_the_first_ten_frames() -> None:
    ref = _poses(30)
    kp, valid = _hands(30)
    sim = ref.copy()
    sim[:10, 0] += 0.05  # 5 cm off during the approach only
    sim[10:, 1] += 0.01  # 1 cm off afterwards
    m = compute_metrics(sim, ref, kp, kp, valid)
    assert m["success"] is False and m["E_t"] == pytest.approx((10 * 5.0 + 20 * 1.0) / 30)
    paper = m["paper"]
    assert paper["first_frame"] == 10 and paper["frames"] == 20
    assert paper["success"] is True and paper["E_t"] == pytest.approx(1.0) and paper["max_E_t"] == pytest.approx(1.0)
    short = compute_metrics(ref[:8], ref[:8], {"right": kp["right"][:8]}, {"right": kp["right"][:8]},
                            {"right": valid["right"][:8]})
    assert short["paper"]["frames"] == 0 and short["paper"]["E_t"] is None  # nothing to average: None, not NaN


def test_penetration_and_the_hand_held_share_of_lifted_frames() -> None:
    from worker.simulation.contacts import contact_frames

    n = 12
    ref = _poses(n)  # rises 0.2 m over 12 frames: lifted (> 2 cm above frame 0) from frame 2 on
    kp, valid = _hands(n)
    table_frames = np.array([0, 1, 2, 3])  # the object leaves the table at frame 4
    rows = np.array([1, 1, 5, 5, 6, 9])  # contact rows' frames; depths in m
    depth = np.array([0.001, 0.003, 0.0, 0.002, 0.0005, 0.004])
    cf = contact_frames(rows, depth, table_frames, n)
    np.testing.assert_allclose(cf.penetration_m[[0, 1, 5, 6, 9]], [0.0, 0.003, 0.002, 0.0005, 0.004])
    m = compute_metrics(ref, ref, kp, kp, valid, cf)
    assert m["penetration_max_mm"] == pytest.approx(4.0)
    assert m["penetration_mean_mm"] == pytest.approx((3.0 + 2.0 + 0.5 + 4.0) / n)
    # Lifted frames 2..11 (10); held by the hand alone: 5, 6, 9 (hand contact, no table).
    assert m["lifted_frames"] == 10 and m["hand_only_fraction"] == pytest.approx(0.3)
    assert m["per_frame"]["hand_only"][[1, 5]].tolist() == [0.0, 1.0]  # frame 1: hand and table
    assert m["paper"]["lifted_frames"] == 2 and m["paper"]["hand_only_fraction"] == 0.0  # frames 10, 11
    assert compute_metrics(ref * [1, 1, 0, 1, 1, 1, 1], ref * [1, 1, 0, 1, 1, 1, 1], kp, kp, valid,
                           cf)["hand_only_fraction"] is None  # never lifted
    with pytest.raises(ValueError, match="frames"):
        contact_frames(np.array([n]), np.array([0.0]), np.zeros(0, dtype=int), n)
