"""The CPU kind a result and a benchmark report record: the model and NumPy's SIMD dispatch."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from common.cpu_kind import cpu_model, numpy_simd

ROOT = Path(__file__).resolve().parents[2]


def test_the_cpu_model_is_named() -> None:
    assert cpu_model().strip()


def test_numpy_simd_follows_what_numpy_may_use() -> None:
    """With every dispatched extension switched off (what a CPU without them gets) only the baseline is left:
    the line tells such a host apart from this one."""
    here = numpy_simd()
    assert here != "unknown"
    off = "" if here == "baseline only" else here
    env = {**os.environ, "NPY_DISABLE_CPU_FEATURES": off, "PYTHONPATH": str(ROOT)}
    code = "from common.cpu_kind import numpy_simd; print(numpy_simd())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "baseline only"
