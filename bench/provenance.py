"""What a benchmark's figures were made with, beyond the code: the commit, the CPU and the numeric packages.

The refinement is a chaotic optimisation: a last-bit difference in one simulated step can send CMA-ES down
another path, so per-sequence figures are reproducible only where all of these match (see
bench/results/refine_dev120.md). ``provenance_line`` states them in one sentence for a report's header.
"""

from __future__ import annotations

import importlib.metadata as md
import subprocess
from pathlib import Path

from common.cpu_kind import cpu_model, numpy_simd

ROOT = Path(__file__).resolve().parents[1]
__all__ = ["KERNELS", "NUMERIC_PACKAGES", "cpu_model", "git_commit", "numpy_simd", "package_versions",
           "provenance_line"]

#: Environments that make NumPy and OpenBLAS compute on this host as on another CPU kind: "avx2" is what an AVX2 host
#: without AVX-512 computes (every x86 host these benchmarks ran on has AVX2), "sse" a host without AVX2. Set before
#: NumPy is imported (``bench/verify_portable.py`` checks a result under each; ``bench/arctic.py --kernels``).
KERNELS: dict[str, dict[str, str]] = {
    "original": {},
    "avx2": {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR AVX512_SKX", "OPENBLAS_CORETYPE": "Haswell"},
    "sse": {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR AVX512_SKX",
            "OPENBLAS_CORETYPE": "Nehalem"},
}
#: Packages whose arithmetic (or whose output feeding the physics) a refinement's figures depend on.
NUMERIC_PACKAGES = ("mujoco", "numpy", "scipy", "cma", "coacd", "trimesh")


def git_commit(root: Path = ROOT) -> str:
    """Short commit of the checkout, with a mark when ``common``/``worker`` differ from it; "unknown" outside git."""
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--", "common", "worker"],
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + (" with uncommitted changes in common/ or worker/" if dirty else "")


def package_versions() -> dict[str, str]:
    out = {}
    for name in NUMERIC_PACKAGES:
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = "absent"
    return out


def provenance_line(code_digest: str) -> str:
    """One sentence for a report header: commit, code digest, CPU, numpy's SIMD dispatch and package versions."""
    versions = ", ".join(f"{k} {v}" for k, v in package_versions().items())
    return (f"Made by commit {git_commit()} (common/ + worker/ digest {code_digest}) on {cpu_model()} "
            f"(numpy SIMD dispatch: {numpy_simd()}); {versions}.")
