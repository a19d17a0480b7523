"""Refinement of a MANO hand (issue #6): MANO's PCA replaces the built-in pose basis, and the result carries
refined MANO parameters (their exactness is tested on ``worker.hand.mano.pose`` directly)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from common.job_options import JobOptions
from common.result_format import read_summary
from tests.support.mano import mano_grasp_sequence
from worker.hand.mano.pose import mano_pca_basis

pytest.importorskip("torch")  # the MANO reference decodes with smplx (the `mano` extra)
pytest.importorskip("smplx")


@pytest.mark.slow
def test_mano_hand_is_refined_in_mano_pca_space_and_returns_mano_parameters(
    mano_dir: Path,
) -> None:
    from worker.refine.prepare import prepare
    from worker.refine.run import refine_sequence

    seq = mano_grasp_sequence(frames=16)
    options = JobOptions(max_generations=1, popsize=4)

    prep = prepare(seq, options, mano_dir=mano_dir)
    basis = prep.spaces["right"].basis
    mano = mano_pca_basis(mano_dir, "right", betas=seq.hands[0].mano.betas, n_components=10)  # type: ignore[union-attr]
    expected_dirs = mano.components[:10] / np.linalg.norm(mano.components[:10], axis=1, keepdims=True)
    np.testing.assert_allclose(basis.components, expected_dirs, atol=1e-12)
    assert "MANO PCA basis for right" in prep.basis_provenance

    outcome = refine_sequence(seq, options, threads=1, mano_dir=mano_dir)
    blob = outcome.to_npz_bytes()
    with np.load(io.BytesIO(blob)) as data:
        keys = set(data.files)
        assert {"right_mano_global_orient", "right_mano_hand_pose", "right_mano_trans"} <= keys
        assert data["right_mano_hand_pose"].shape == (16, 45)
        assert np.all(np.isfinite(data["right_mano_hand_pose"]))
    assert "MANO" in read_summary(blob)["config"]["pose_basis"]
