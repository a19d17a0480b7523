"""MANO hands through the physics (issue #6 item 3): ``retarget_sequence`` picks the MANO reference when the
model files are configured, IK on keypoints otherwise, and the clear error for MANO-only hands without them;
the scene's hand is then the subject's MANO mesh (per-part convex hulls, same bodies and hinges); ``hoi-refine
replay`` runs a MANO-only sequence end to end on the synthetic MANO model."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import mujoco
import numpy as np
import pytest

from common.errors import ManoModelMissingError
from common.result_format import read_contacts, read_summary
from common.sequence import ManoParams
from common.sequence_io import save_sequence
from tests.support.mano import T, mano_grasp_sequence, use_mano_dir
from worker.hand.mano import ensure_keypoints
from worker.hand.retarget import retarget_sequence
from worker.simulation.scene import Scene, build_scene

pytest.importorskip("torch")  # the MANO reference decodes with smplx (the `mano` extra)
pytest.importorskip("smplx")

def test_retarget_sequence_dispatch(mano_dir: Path) -> None:
    seq = mano_grasp_sequence()
    decoded = ensure_keypoints(seq, mano_dir)
    (ref,) = retarget_sequence(seq, mano_dir=mano_dir)
    assert "mano_vertices" in ref.geometry.meta  # the subject's MANO hand, not a fitted built-in one
    kp = decoded.keypoints_world(decoded.hands[0])
    np.testing.assert_allclose(ref.fitted_keypoints()[1:], kp[1:], atol=2e-3)  # tips: pose correctives only
    np.testing.assert_allclose(ref.keypoints[0], ref.fitted_keypoints()[0])  # invalid frame: the MANO hand's
    # Keypoints and MANO: still the MANO hand, the observation as target.
    (ref_kp,) = retarget_sequence(decoded, mano_dir=mano_dir)
    assert "mano_vertices" in ref_kp.geometry.meta and ref_kp.mean_residual_mm() < 2.0
    np.testing.assert_allclose(ref_kp.keypoints[1:], kp[1:])

    (ik,) = retarget_sequence(decoded)  # no model: IK on the keypoints, as for any keypoint hand
    assert "frames_used" in ik.geometry.meta and ik.mean_residual_mm() < 3.0
    with pytest.raises(ManoModelMissingError, match=r"MANO_RIGHT\.pkl.*HOI_REFINE_MANO_DIR is not set"):
        retarget_sequence(seq)
    empty = dataclasses.replace(seq.hands[0], valid=np.zeros(T, bool))
    with pytest.raises(Exception, match="no frame has a valid hand"):
        retarget_sequence(dataclasses.replace(seq, hands=[empty]), mano_dir=mano_dir)


def test_replay_cli_mano_only(
    mano_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from common.cli import main

    src, out = tmp_path / "mano.npz", tmp_path / "result.npz"
    save_sequence(mano_grasp_sequence(), src)
    use_mano_dir(monkeypatch, None)
    assert main(["replay", str(src), "--out", str(out)]) == 2 and not out.exists()
    use_mano_dir(monkeypatch, mano_dir)
    capsys.readouterr()
    assert main(["inspect", str(src)]) == 0 and "the MANO hand is used" in capsys.readouterr().out
    assert main(["replay", str(src), "--out", str(out)]) == 0
    summary = read_summary(out.read_bytes())
    assert summary["frames"] == T and summary["ik_residual_mm"]["right"] == 0.0
    contacts = read_contacts(out.read_bytes())
    assert summary["num_contacts"] == len(contacts) > 0 and {c["hand"] for c in contacts} == {"right"}


def _part_world_vertices(scene: Scene, data: mujoco.MjData, part: str) -> np.ndarray:
    model = scene.model
    geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"right_{part}")
    assert model.geom_type[geom] == mujoco.mjtGeom.mjGEOM_MESH, part
    mesh = model.geom_dataid[geom]
    verts = model.mesh_vert[model.mesh_vertadr[mesh] : model.mesh_vertadr[mesh] + model.mesh_vertnum[mesh]]
    return np.asarray(data.geom_xpos[geom] + verts @ data.geom_xmat[geom].reshape(3, 3).T)


def test_scene_hand_is_the_mano_mesh(mano_dir: Path) -> None:
    """Every hand body carries its MANO part hull; posed by the reference, the hulls lie on the MANO mesh that
    smplx poses from the same parameters (up to pose correctives and blend skinning near the joints)."""
    from worker.hand.mano.decode import decode_mano, load_mano_model
    from worker.hand.mano.synthetic_model import MANO_FINGER_START
    from worker.hand.model import BODY_PARTS, default_geometry
    from worker.simulation.hand_mjcf import hand_mjcf

    seq = mano_grasp_sequence()
    (ref,) = retarget_sequence(seq, mano_dir=mano_dir)
    scene = build_scene(seq, [ref])
    capsule_scene = build_scene(seq, [dataclasses.replace(ref, geometry=default_geometry("right"))])
    for attr in ("njnt", "nu", "nsensor", "nsite", "nbody"):  # same bodies, hinges, servos, sites, sensors
        assert getattr(scene.model, attr) == getattr(capsule_scene.model, attr), attr
    assert 'type="mesh"' not in capsule_scene.xml and "right_palm_hull" in scene.xml
    mujoco.MjModel.from_xml_string(hand_mjcf(ref.geometry))  # the standalone hand compiles too

    t, hand = 4, scene.hands["right"]
    data = scene.make_data()
    posed = decode_mano(seq.hands[0].mano, "right", mano_dir, return_vertices=True).vertices  # type: ignore[arg-type]
    assert posed is not None
    world = seq.world_transform()
    mesh = posed[t] @ world[:3, :3].T + world[:3, 3]
    part_of = np.asarray(load_mano_model("right", mano_dir).data["weights"]).argmax(axis=1)
    joint = dict(zip(BODY_PARTS, [0] + [s + j for s in MANO_FINGER_START for j in range(3)], strict=True))

    def max_gap_mm(q: np.ndarray) -> float:
        data.qpos[hand.root_qpos_adr : hand.root_qpos_adr + 7] = np.concatenate([ref.wrist_pos[t], ref.wrist_quat[t]])
        data.qpos[hand.qpos_adr] = q
        mujoco.mj_kinematics(scene.model, data)
        gaps = [
            np.linalg.norm(_part_world_vertices(scene, data, p)[:, None] - mesh[part_of == k][None], axis=2).min(1)
            for p, k in joint.items()
        ]
        return 1e3 * float(np.concatenate(gaps).max())

    assert max_gap_mm(ref.q[t]) < 2.5
    assert max_gap_mm(np.zeros(45)) > 10.0  # the check above can fail: an unposed hand is far off


def test_part_meshes_are_checked() -> None:
    from worker.hand.model import default_geometry
    from worker.simulation.hand_mjcf import hand_asset_xml

    geo = default_geometry("left")
    assert hand_asset_xml(geo) == ""
    cube = np.array([[x, y, z] for x in (0, 0.01) for y in (0, 0.01) for z in (0, 0.01)])
    with_mesh = dataclasses.replace(geo, part_meshes={"index2": cube})
    assert hand_asset_xml(with_mesh).startswith('<mesh name="left_index2_hull"')
    with pytest.raises(ValueError, match="unknown body 'index4'"):
        dataclasses.replace(geo, part_meshes={"index4": cube})
    with pytest.raises(ValueError, match=r"part_meshes\['palm'\] must have shape"):
        dataclasses.replace(geo, part_meshes={"palm": cube[:3]})


def test_raw_replay_result_carries_mano_params(mano_dir: Path) -> None:
    """A MANO hand's replay result holds ``right_mano_*`` parameters that decode to the input hand (the driven
    reference is exact); a keypoint hand's result holds none."""
    from common.result_format import read_arrays
    from worker.hand.mano.decode import decode_mano
    from worker.simulation.replay import raw_replay, replay_result_bytes

    seq = mano_grasp_sequence(5)
    blob = replay_result_bytes(raw_replay(seq, record_contacts=True, mano_dir=mano_dir))
    arrays = read_arrays(blob)
    assert read_summary(blob)["hand_model"] == {"right": "MANO"}
    back = ManoParams(
        arrays["right_mano_global_orient"], arrays["right_mano_hand_pose"], arrays["right_mano_trans"],
        arrays["right_mano_betas"], str(arrays["right_mano_pose_format"]),  # type: ignore[arg-type]
        bool(arrays["right_mano_flat_hand_mean"]),
    )  # fmt: skip
    np.testing.assert_allclose(back.betas, seq.hands[0].mano.betas)  # type: ignore[union-attr]
    want = decode_mano(seq.hands[0].mano, "right", mano_dir).keypoints  # type: ignore[arg-type]
    back_kp = decode_mano(back, "right", mano_dir).keypoints
    np.testing.assert_allclose(back_kp[1:], want[1:], atol=1e-8)  # frame 0 invalid

    keypoint_hand = dataclasses.replace(ensure_keypoints(seq, mano_dir).hands[0], mano=None)
    arrays = read_arrays(replay_result_bytes(raw_replay(dataclasses.replace(seq, hands=[keypoint_hand]))))
    assert "right_q_target" in arrays and not any("mano" in k for k in arrays)
