"""MANO through smplx on the synthetic MANO-format model: keypoints, PCA / axis-angle, flat_hand_mean,
the exact MANO -> built-in hand conversion and back, ensure_keypoints, and MANO's PCA over the hinges."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from common.sequence import HandTrack, ManoParams, ObjectSpec, Sequence
from worker.hand.mano import ensure_keypoints, load_mano_pickle
from worker.hand.mano.decode import MANO21_ORDER, decode_mano
from worker.hand.mano.hand_geometry import mano_hand_geometry
from worker.hand.mano.pose import (
    hand_pose_to_mano,
    mano_hand_pose,
    mano_pca_basis,
    mano_reference,
    mano_result_arrays,
    refined_mano_params,
)
from worker.hand.mano.synthetic_model import MANO_PARENTS
from worker.hand.model import forward_keypoints

pytest.importorskip("torch")
pytest.importorskip("smplx")

T = 4



def _params(rng: np.random.Generator, pose_format: str = "axis_angle", n: int = 45, flat: bool = True) -> ManoParams:
    return ManoParams(
        global_orient=rng.normal(0, 1.0, (T, 3)), hand_pose=rng.normal(0, 0.4, (T, n)),
        trans=rng.normal(0, 0.2, (T, 3)), betas=rng.normal(0, 1.0, 10),
        pose_format=pose_format, flat_hand_mean=flat,  # type: ignore[arg-type]
    )  # fmt: skip


def _numpy_joints(params: ManoParams, data: dict, hand_pose_aa: np.ndarray) -> np.ndarray:
    """Independent forward kinematics of MANO's 16 joints (joints do not depend on pose correctives)."""
    v = data["v_template"] + data["shapedirs"] @ params.betas
    rest = data["J_regressor"] @ v
    aa = np.concatenate([params.global_orient, hand_pose_aa], axis=1).reshape(T, 16, 3)
    out = np.zeros((T, 16, 3))
    for t in range(T):
        glob = [np.eye(3)] * 16
        for k in range(16):
            r = Rotation.from_rotvec(aa[t, k]).as_matrix()
            p = MANO_PARENTS[k]
            glob[k] = r if p < 0 else glob[p] @ r
            out[t, k] = rest[0] if p < 0 else out[t, p] - params.trans[t] + glob[p] @ (rest[k] - rest[p])
            out[t, k] += params.trans[t]
    return out


def test_keypoints_match_independent_kinematics(mano_dir: Path) -> None:
    data = load_mano_pickle(mano_dir / "MANO_RIGHT.pkl")
    params = _params(np.random.default_rng(0), flat=True)
    dec = decode_mano(params, "right", mano_dir, return_vertices=True)
    assert dec.keypoints.shape == (T, 21, 3) and dec.rotations.shape == (T, 16, 3, 3)
    assert dec.vertices is not None and dec.vertices.shape == (T, len(data["v_template"]), 3)
    joints = _numpy_joints(params, data, params.hand_pose)
    np.testing.assert_allclose(dec.joints, joints, atol=1e-6)
    # MANO21 order: 16 joints reordered + the 5 tip vertices (thumb, index, middle, ring, pinky).
    full = np.concatenate([joints, dec.vertices[:, list(data["tip_vertex_ids"])]], axis=1)
    np.testing.assert_allclose(dec.keypoints, full[:, list(MANO21_ORDER)], atol=1e-6)
    np.testing.assert_allclose(dec.keypoints[:, 0], joints[:, 0])  # wrist
    np.testing.assert_allclose(dec.keypoints[:, 1], joints[:, 13])  # thumb CMC
    np.testing.assert_allclose(dec.keypoints[:, 17], joints[:, 7])  # pinky MCP


def test_pca_and_flat_hand_mean(mano_dir: Path) -> None:
    data = load_mano_pickle(mano_dir / "MANO_LEFT.pkl")
    rng = np.random.default_rng(1)
    for n in (6, 45):  # 45 is DexYCB's ncomps, which smplx itself would treat as axis-angle
        pca = _params(rng, "pca", n, flat=False)
        aa = ManoParams(pca.global_orient, pca.hand_pose @ data["hands_components"][:n] + data["hands_mean"],
                        pca.trans, pca.betas, "axis_angle", True)  # fmt: skip
        a, b = decode_mano(pca, "left", mano_dir), decode_mano(aa, "left", mano_dir)
        np.testing.assert_allclose(a.keypoints, b.keypoints, atol=1e-9)
        np.testing.assert_allclose(a.joints, _numpy_joints(aa, data, aa.hand_pose), atol=1e-6)
    flat = _params(rng, flat=True)
    not_flat = ManoParams(flat.global_orient, flat.hand_pose - data["hands_mean"], flat.trans, flat.betas,
                          "axis_angle", False)  # fmt: skip
    np.testing.assert_allclose(
        decode_mano(flat, "left", mano_dir).keypoints, decode_mano(not_flat, "left", mano_dir).keypoints, atol=1e-9
    )


@pytest.mark.parametrize("side", ["right", "left"])
def test_builtin_hand_reproduces_mano_and_back(mano_dir: Path, side: str) -> None:
    params = _params(np.random.default_rng(2), "pca", 45, flat=False)
    dec = decode_mano(params, side, mano_dir)  # type: ignore[arg-type]
    mgeo = mano_hand_geometry(mano_dir, side, params.betas)  # type: ignore[arg-type]
    pos, rot, q = mano_hand_pose(params, mgeo, mano_dir)
    quat = Rotation.from_matrix(rot).as_quat(scalar_first=True)
    kp = forward_keypoints(mgeo.geometry, pos, quat, q)
    err = np.linalg.norm(kp - dec.keypoints, axis=2)
    assert err[:, [i for i in range(21) if i % 4]].max() < 1e-6  # joints: exact
    assert err[:, [4, 8, 12, 16, 20]].max() < 2e-3  # tips move a little with MANO's pose correctives
    for fmt in ("axis_angle", "pca"):
        back = hand_pose_to_mano(pos, quat, q, mgeo, params.betas, mano_dir, pose_format=fmt)
        np.testing.assert_allclose(decode_mano(back, side, mano_dir).keypoints, dec.keypoints, atol=1e-9)  # type: ignore[arg-type]
    np.testing.assert_allclose(back.hand_pose, params.hand_pose, atol=1e-8)  # PCA 45 is a change of basis


def test_ensure_keypoints_and_reference(mano_dir: Path) -> None:
    params = _params(np.random.default_rng(3), "pca", 10, flat=False)
    valid = np.array([False, True, True, True])
    world = np.eye(4)
    world[:3, :3] = Rotation.from_euler("x", -120, degrees=True).as_matrix()
    world[:3, 3] = [0.1, -0.2, 0.7]
    seq = Sequence(
        name="mano", fps=30.0,
        object=ObjectSpec(name="box", mass_kg=0.1, primitive="box", size=np.array([0.02, 0.02, 0.02])),
        object_pose=np.tile([0.0, 0, 0.02, 1, 0, 0, 0], (T, 1)),
        hands=[HandTrack(side="right", valid=valid, mano=params)], world_from_source=world,
    ).validate()  # fmt: skip
    out = ensure_keypoints(seq, mano_dir)
    assert out is not seq and seq.hands[0].keypoints is None
    kp = out.hands[0].keypoints
    assert kp is not None and np.all(kp[0] == 0.0)
    np.testing.assert_allclose(kp[1:], decode_mano(params, "right", mano_dir).keypoints[1:])
    ref = mano_reference(out, out.hands[0], mano_dir)
    np.testing.assert_allclose(ref.keypoints[1:, :4], out.keypoints_world(out.hands[0])[1:, :4], atol=1e-6)
    np.testing.assert_allclose(ref.wrist_pos[0], ref.wrist_pos[1])  # invalid frame held at the nearest valid
    # The world-frame reference maps back to MANO parameters that decode to the same source keypoints.
    back = refined_mano_params(out, out.hands[0], ref.wrist_pos, ref.wrist_quat, ref.q, mano_dir, pose_format="pca")
    np.testing.assert_allclose(back.hand_pose[1:], params.hand_pose[1:] @ np.eye(10, 45), atol=1e-8)
    np.testing.assert_allclose(decode_mano(back, "right", mano_dir).keypoints[1:], kp[1:], atol=1e-9)
    arrays = mano_result_arrays(out, out.hands[0], ref.wrist_pos, ref.wrist_quat, ref.q, mano_dir)
    assert str(arrays["right_mano_pose_format"]) == "axis_angle" and arrays["right_mano_hand_pose"].shape == (T, 45)


def test_pca_basis_over_hinges(mano_dir: Path) -> None:
    basis = mano_pca_basis(mano_dir, "right", n_components=10)
    assert basis.mean.shape == (45,) and basis.components.shape == (10, 45)
    assert basis.components_axis_angle.shape == (10, 45)
    # q(mean + B·c) ≈ q_mean + c @ components for small coefficients (the linearisation the refinement uses).
    c = np.random.default_rng(4).normal(0, 0.02, 10)
    mgeo = mano_hand_geometry(mano_dir, "right", np.zeros(10))
    params = ManoParams(np.zeros((1, 3)), c[None], np.zeros((1, 3)), np.zeros(10), "pca", False)
    q = mano_hand_pose(params, mgeo, mano_dir)[2][0]
    np.testing.assert_allclose(q, basis.mean + c @ basis.components, atol=2e-3)
    assert np.abs(q - basis.mean).max() > 0.02  # the check above is not trivially met
