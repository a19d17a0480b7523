"""bench/arctic.py's plan key and forced kernels (no ARCTIC data needed)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import bench.arctic as arctic

ROOT = Path(__file__).resolve().parents[2]


def test_rows_of_other_kernels_or_plans_do_not_answer_for_each_other() -> None:
    keys = {arctic.plan_key(arctic.parse_args(["--arctic", "x", *extra]))
            for extra in ([], ["--kernels", "avx2"], ["--kernels", "sse"], ["--restarts", "0"], ["--no-polish"],
                          ["--cma", "rewind_windows=3"], ["--seed", "1"])}  # fmt: skip
    assert len(keys) == 7


def test_forced_kernels_run_the_bench_again_under_them(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("NPY_DISABLE_CPU_FEATURES", "OPENBLAS_CORETYPE")}
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "arctic.py"), "--arctic", str(tmp_path), "--kernels",
                          "sse"], capture_output=True, text=True, env=env, timeout=120)  # fmt: skip
    assert out.returncode == 2, out.stderr  # no sequences in an empty folder
    assert "NumPy / OpenBLAS kernels: sse; NumPy dispatches to: baseline only" in out.stderr
    plain = subprocess.run([sys.executable, str(ROOT / "bench" / "arctic.py"), "--arctic", str(tmp_path)],
                           capture_output=True, text=True, env=env, timeout=120)  # fmt: skip
    assert plain.returncode == 2 and "NumPy / OpenBLAS kernels" not in plain.stderr


def test_another_seeds_result_is_stored_beside_the_first_not_over_it() -> None:
    assert arctic.result_name("s01/mixer_use_01", "per_hand") == "s01_mixer_use_01_per_hand.result.npz"
    assert arctic.result_name("s01/mixer_use_01", "per_hand", 2) == "s01_mixer_use_01_per_hand_s2.result.npz"
