"""A benchmark report names what its figures depend on: commit, CPU, NumPy's SIMD dispatch, package versions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.provenance import NUMERIC_PACKAGES, cpu_model, git_commit, numpy_simd, package_versions, provenance_line

ROOT = Path(__file__).resolve().parents[2]


def test_the_line_names_commit_digest_cpu_and_every_numeric_package() -> None:
    line = provenance_line("0123456789ab")
    assert "digest 0123456789ab" in line
    assert f"numpy {np.__version__}" in line
    for name in NUMERIC_PACKAGES:
        assert f"{name} " in line
    assert package_versions()["numpy"] == np.__version__
    assert f"on {cpu_model()} (numpy SIMD dispatch: {numpy_simd()})" in line


def test_the_commit_is_read_from_git_or_said_unknown(tmp_path: Path) -> None:
    assert git_commit(tmp_path) == "unknown"  # not a checkout
    here = git_commit(ROOT)
    if (ROOT / ".git").exists():
        assert here.split()[0] != "unknown" and len(here.split()[0]) >= 7
