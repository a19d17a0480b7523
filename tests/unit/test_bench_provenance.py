"""A benchmark report names what its figures depend on: commit, CPU, NumPy's SIMD dispatch, package versions."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench.provenance import NUMERIC_PACKAGES, git_commit, numpy_simd, package_versions, provenance_line

ROOT = Path(__file__).resolve().parents[2]


def test_the_line_names_commit_digest_cpu_and_every_numeric_package() -> None:
    line = provenance_line("0123456789ab")
    assert "digest 0123456789ab" in line
    assert f"numpy {np.__version__}" in line
    for name in NUMERIC_PACKAGES:
        assert f"{name} " in line
    assert package_versions()["numpy"] == np.__version__


def test_the_commit_is_read_from_git_or_said_unknown(tmp_path: Path) -> None:
    assert git_commit(tmp_path) == "unknown"  # not a checkout
    here = git_commit(ROOT)
    if (ROOT / ".git").exists():
        assert here.split()[0] != "unknown" and len(here.split()[0]) >= 7


def test_numpy_simd_follows_what_numpy_may_use() -> None:
    """With every dispatched extension switched off (what a CPU without them gets) only the baseline is left:
    the line tells such a host apart from this one."""
    here = numpy_simd()
    assert here != "unknown"
    off = "" if here == "baseline only" else here
    env = {**os.environ, "NPY_DISABLE_CPU_FEATURES": off, "PYTHONPATH": str(ROOT)}
    code = "from bench.provenance import numpy_simd; print(numpy_simd())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "baseline only"
