"""An ARCTIC release sequence's hands are MANO parameters: decoded with the user's MANO files (here the project's
synthetic MANO-format model), and refused with the error naming ``HOI_REFINE_MANO_DIR`` without them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from common.cli import main
from common.sequence_io import load_sequence
from tests.support.arctic_tree import write_release_tree
from tests.support.mano import use_mano_dir
from worker.hand.mano import ensure_keypoints, load_mano_pickle


@pytest.mark.parametrize("command", [["inspect"], ["replay"], ["refine", "--out", "r.npz"]])
def test_without_mano_files_the_commands_name_the_setting(
    command: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    use_mano_dir(monkeypatch, None)
    mano_path = write_release_tree(tmp_path)
    monkeypatch.chdir(tmp_path)
    assert main([command[0], str(mano_path), *command[1:]]) == 2
    err = capsys.readouterr().err
    assert "HOI_REFINE_MANO_DIR" in err and "Traceback" not in err
    assert not (tmp_path / "r.npz").exists()


def test_release_hands_decode_with_the_mano_model(tmp_path: Path, mano_dir: Path) -> None:
    pytest.importorskip("torch")
    pytest.importorskip("smplx")
    seq = load_sequence(write_release_tree(tmp_path))
    decoded = ensure_keypoints(seq, mano_dir)
    assert decoded.meta["keypoints_from"] == "MANO (smplx)"
    for hand in decoded.hands:
        assert hand.keypoints is not None and hand.keypoints.shape == (3, 21, 3)
        assert np.isfinite(hand.keypoints).all()
        m = hand.mano
        assert m is not None
        # The wrist is MANO's root joint: the global rotation turns the hand about it, so it sits at the shaped
        # template's root plus the translation whatever the pose.
        model = load_mano_pickle(mano_dir / f"MANO_{hand.side.upper()}.pkl")
        shaped = model["v_template"] + model["shapedirs"] @ m.betas
        root = np.asarray(model["J_regressor"] @ shaped)[0]
        np.testing.assert_allclose(hand.keypoints[:, 0], root + m.trans, atol=1e-6)
        # The pose moves the fingers: the fingertips differ between frames relative to the wrist.
        tips = hand.keypoints[:, [4, 8, 12, 16, 20]] - hand.keypoints[:, :1]
        assert np.abs(tips[1] - tips[0]).max() > 1e-3
    # The decoded sequence is still the articulated object.
    np.testing.assert_array_equal(decoded.articulation, seq.articulation)
