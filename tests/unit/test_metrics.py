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
