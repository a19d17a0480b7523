"""A DexYCB native sequence without camera labels: its hands are MANO only, decoded through smplx with the
test MANO model; without a model, loading and ``hoi-refine inspect`` fail with the clear error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from common.errors import ManoModelMissingError
from common.sequence import HandTrack, ManoParams, ObjectSpec, Sequence
from common.sequence_io import load_sequence, save_sequence
from common.settings import get_settings
from worker.hand.mano import build_test_mano_model, ensure_keypoints
from worker.hand.mano.decode import decode_mano

T = 5


def _tree(root: Path) -> Path:
    """One DexYCB sequence (right hand, no labels), table frame = master camera moved 0.5 m."""
    apriltag = np.hstack([np.eye(3), [[0.0], [0.0], [-0.5]]])  # master_from_table
    extr = root / "calibration" / "extrinsics_x"
    extr.mkdir(parents=True)
    cameras = {"111": np.eye(3, 4).ravel().tolist(), "apriltag": apriltag.ravel().tolist()}
    (extr / "extrinsics.yml").write_text(yaml.safe_dump({"master": "111", "extrinsics": cameras}))
    (root / "calibration" / "mano_s1").mkdir()
    (root / "calibration" / "mano_s1" / "mano.yml").write_text(yaml.safe_dump({"betas": [0.3] + [0.0] * 9}))
    mesh = root / "models" / "061_foam_brick" / "textured_simple.obj"
    mesh.parent.mkdir(parents=True)
    mesh.write_text("v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\nv 0 0 0.05\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    seq = root / "20200709-subject-01" / "20200709_141754"
    seq.mkdir(parents=True)
    pose_y = np.zeros((T, 1, 7))
    pose_y[:, 0] = [0, 0, 0, 1, 0.0, 0.0, -0.5]
    pose_m = np.random.default_rng(0).normal(0, 0.2, (T, 1, 51))
    pose_m[0] = 0.0
    np.savez(seq / "pose.npz", pose_y=pose_y, pose_m=pose_m)
    (seq / "meta.yml").write_text(yaml.safe_dump({
        "serials": ["111"], "num_frames": T, "ycb_ids": [21], "ycb_grasp_ind": 0, "mano_sides": ["right"],
        "mano_calib": ["s1"], "extrinsics": "x"}))  # fmt: skip
    return seq


def test_dexycb_mano_only_hand_is_decoded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("torch")
    pytest.importorskip("smplx")
    seq_dir = _tree(tmp_path / "dexycb")
    (tmp_path / "mano").mkdir()
    build_test_mano_model(tmp_path / "mano", "right")
    monkeypatch.setenv("HOI_REFINE_MANO_DIR", str(tmp_path / "mano"))
    get_settings.cache_clear()
    seq = ensure_keypoints(load_sequence(seq_dir), tmp_path / "mano")
    hand = seq.hands[0]
    assert hand.mano is not None and hand.keypoints is not None
    np.testing.assert_array_equal(hand.valid, [False] + [True] * (T - 1))
    np.testing.assert_allclose(hand.mano.betas, [0.3] + [0.0] * 9)
    np.testing.assert_allclose(hand.keypoints[1:], decode_mano(hand.mano, "right", tmp_path / "mano").keypoints[1:])
    assert seq.object.name == "061_foam_brick" and seq.object.mass_kg == pytest.approx(0.028)
    # World = table frame: the camera-frame point (0, 0, -0.5) is the table origin.
    np.testing.assert_allclose(seq.object_pose_world()[:, :3], 0.0, atol=1e-12)


def test_inspect_reports_missing_model(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                       capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    monkeypatch.delenv("HOI_REFINE_MANO_DIR", raising=False)
    get_settings.cache_clear()
    seq_dir = _tree(tmp_path / "dexycb")
    with pytest.raises(ManoModelMissingError, match="HOI_REFINE_MANO_DIR"):
        load_sequence(seq_dir)
    mano = ManoParams(np.zeros((T, 3)), np.zeros((T, 45)), np.zeros((T, 3)), np.zeros(10))
    npz = tmp_path / "mano_only.npz"
    save_sequence(Sequence(
        name="mano-only", fps=30.0,
        object=ObjectSpec(name="box", mass_kg=0.1, primitive="box", size=np.array([0.02, 0.02, 0.02])),
        object_pose=np.tile([0.0, 0, 0.02, 1, 0, 0, 0], (T, 1)),
        hands=[HandTrack(side="right", valid=np.ones(T, bool), mano=mano)]).validate(), npz)  # fmt: skip
    try:
        from common.cli import build_parser, main

        build_parser().parse_args(["inspect", str(npz)])
    except (ImportError, SystemExit):
        pytest.skip("`hoi-refine inspect` is not wired yet")
    for target in (seq_dir, npz):
        assert main(["inspect", str(target)]) == 2
        err = capsys.readouterr().err
        assert "HOI_REFINE_MANO_DIR is not set" in err and "MANO_RIGHT.pkl" in err, err
