"""Pose basis: PCA recovers a known low-rank structure; the packaged basis loads with its provenance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from common.errors import ConfigurationError
from worker.hand.pose_basis import POSE_BASIS_FILE, fit_pose_basis, load_pose_basis, save_pose_basis


def test_pca_recovers_a_known_subspace(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    basis_true = np.linalg.qr(rng.normal(size=(45, 3)))[0].T  # 3 orthonormal directions
    coeffs = rng.normal(size=(500, 3)) * [0.5, 0.2, 0.1]
    q = 0.3 + coeffs @ basis_true + rng.normal(0, 1e-4, (500, 45))
    pb = fit_pose_basis(q, n_components=5, provenance={"data": "synthetic"})
    assert pb.components.shape == (5, 45)
    np.testing.assert_allclose(pb.components @ pb.components.T, np.eye(5), atol=1e-9)
    assert pb.explained_variance_ratio[:3].sum() > 0.999
    np.testing.assert_allclose(pb.stddev[:3], [0.5, 0.2, 0.1], rtol=0.1)
    # The first 3 components span the true subspace.
    proj = basis_true @ pb.components[:3].T
    np.testing.assert_allclose(np.linalg.svd(proj, compute_uv=False), 1.0, atol=1e-3)
    np.testing.assert_allclose(pb.to_hinges(np.ones(2)), pb.stddev[:2] @ pb.components[:2])
    path = tmp_path / "pb.npz"
    save_pose_basis(path, pb)
    back = load_pose_basis(path)
    np.testing.assert_array_equal(back.components, pb.components)
    assert back.provenance == {"data": "synthetic"} and back.truncated(2).components.shape == (2, 45)


def test_missing_file_is_a_configuration_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigurationError, match="make pose-basis"):
        load_pose_basis(tmp_path / "missing.npz")


def test_packaged_basis_has_provenance() -> None:
    if not POSE_BASIS_FILE.is_file():
        pytest.skip("worker/hand/data/pose_basis.npz has not been built")
    pb = load_pose_basis()
    assert pb.mean.shape == (45,) and pb.components.shape[0] >= 10
    assert np.all(np.diff(pb.stddev) <= 1e-12)  # ordered by variance
    for key in ("data", "frames", "date", "git_commit"):
        assert key in pb.provenance
    assert pb.provenance["frames"] > 1000
    assert pb.explained_variance_ratio[:10].sum() > 0.8  # hand poses are low-dimensional
