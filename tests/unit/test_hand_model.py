"""The built-in hand: MJCF kinematics equal the NumPy reference, geometry fitting recovers the hand."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from common.geometry import cross
from worker.hand.model import (
    AXIS_VECTORS,
    HINGE_NAMES,
    JOINT_LOWER,
    JOINT_UPPER,
    default_geometry,
    finger_kinematics,
    fit_hand_geometry,
    forward_keypoints,
)
from worker.simulation.hand_mjcf import hand_mjcf


def test_hinge_names_and_limits() -> None:
    assert len(HINGE_NAMES) == 45 == len(set(HINGE_NAMES))
    assert HINGE_NAMES[0] == "thumb1_abd" and HINGE_NAMES[-1] == "pinky3_twist"
    assert np.all(JOINT_LOWER < 0) and np.all(JOINT_UPPER > 0)


@pytest.mark.parametrize("side", ["right", "left"])
def test_mjcf_sites_match_forward_keypoints(side: str) -> None:
    geometry = default_geometry(side, 0.19)  # type: ignore[arg-type]
    model = mujoco.MjModel.from_xml_string(hand_mjcf(geometry))
    data = mujoco.MjData(model)
    rng = np.random.default_rng(3)
    q = rng.uniform(JOINT_LOWER, JOINT_UPPER)
    data.qpos[[model.jnt_qposadr[model.joint(f"{side}_{n}").id] for n in HINGE_NAMES]] = q
    quat = rng.normal(size=4)
    data.qpos[:7] = [0.1, -0.2, 0.3, *(quat / np.linalg.norm(quat))]
    mujoco.mj_forward(model, data)
    sim = np.array([data.site(f"{side}_kp{j}").xpos for j in range(21)])
    ref = forward_keypoints(geometry, data.qpos[:3], data.qpos[3:7], q)
    np.testing.assert_allclose(sim, ref, atol=1e-6)
    assert model.nu == 45 and model.nbody == 18  # world, mocap, palm, 15 segments
    assert 0.2 < model.body_subtreemass[model.body(f"{side}_palm").id] < 0.6  # tissue density, kg


def test_left_hand_mirrors_right() -> None:
    right, left = default_geometry("right"), default_geometry("left")
    np.testing.assert_allclose(left.bases * [1, -1, 1], right.bases)
    q = np.random.default_rng(0).uniform(JOINT_LOWER, JOINT_UPPER) * 0.5
    q_mirror = q.copy()
    q_mirror[0::3] *= -1  # abduction and twist change sign in a mirror, flexion does not
    q_mirror[2::3] *= -1
    kr = forward_keypoints(right, np.zeros(3), np.array([1.0, 0, 0, 0]), q)
    kl = forward_keypoints(left, np.zeros(3), np.array([1.0, 0, 0, 0]), q_mirror)
    np.testing.assert_allclose(kl * [1, -1, 1], kr, atol=1e-9)


def test_fit_recovers_bone_lengths_and_palm() -> None:
    truth = default_geometry("right", 0.17)
    rng = np.random.default_rng(1)
    q = rng.uniform(0.6 * JOINT_LOWER, 0.6 * JOINT_UPPER, (30, 45))
    quat = rng.normal(size=(30, 4))
    kp = forward_keypoints(truth, rng.normal(size=(30, 3)), quat / np.linalg.norm(quat, axis=1, keepdims=True), q)
    valid = np.ones(30, dtype=bool)
    valid[::7] = False
    kp[~valid] = 0.0  # invalid frames hold garbage and must be ignored
    fitted = fit_hand_geometry(kp, valid, "right")
    np.testing.assert_allclose(fitted.lengths, truth.lengths, atol=1e-9)
    np.testing.assert_allclose(fitted.bases, truth.bases, atol=1e-9)
    assert fitted.hand_length == pytest.approx(truth.hand_length)


def test_fit_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="keypoints_world"):
        fit_hand_geometry(np.zeros((5, 20, 3)), np.ones(5, dtype=bool), "right")
    with pytest.raises(ValueError, match="valid"):
        fit_hand_geometry(np.zeros((5, 21, 3)), np.ones(4, dtype=bool), "right")


def test_cross_is_numpys_bit_for_bit() -> None:
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(5, 1, 9, 3)), rng.normal(size=(5, 3, 9, 3))  # broadcast as in the IK's Jacobian
    np.testing.assert_array_equal(cross(a, b), np.cross(a, b))


def test_finger_kinematics_is_the_textbook_rodrigues_chain_bit_for_bit() -> None:
    # The retargeting's results (and every stored result made from them) depend on these exact bits: the
    # precomputed hinge-axis parts must give what building Rodrigues' formula afresh per call gave.
    geometry = default_geometry("right")
    q = np.random.default_rng(5).uniform(JOINT_LOWER, JOINT_UPPER, size=(7, 45))

    def rodrigues(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
        c, s = np.cos(angles)[..., None, None], np.sin(angles)[..., None, None]
        k = np.zeros((*axes.shape[:-1], 3, 3))
        k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -axes[..., 2], axes[..., 1], -axes[..., 0]
        k = k - np.swapaxes(k, -1, -2)
        outer = axes[..., :, None] * axes[..., None, :]
        return c * np.eye(3) + s * k + (1 - c) * outer

    rot = np.broadcast_to(geometry.rest_rot, (7, 5, 3, 3)).copy()
    pos = np.broadcast_to(geometry.bases, (7, 5, 3)).copy()
    qf = q.reshape(7, 5, 9)
    for j in range(3):
        for h in range(3):
            rot = rot @ rodrigues(np.broadcast_to(AXIS_VECTORS[h], (7, 5, 3)), qf[:, :, 3 * j + h])
        pos = pos + rot[..., 0] * geometry.lengths[:, j, None]
        np.testing.assert_array_equal(finger_kinematics(geometry, q).points[:, :, j], pos)
