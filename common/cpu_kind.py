"""The CPU a computation ran on, as far as its figures depend on it: the model and NumPy's SIMD dispatch.

MuJoCo's arithmetic is the same on every x86_64 host, but NumPy picks vectorised kernels by the CPU's extensions
(AVX2, AVX-512, ...) whose last bits differ, and contact-rich dynamics and a chaotic optimisation grow those
bits: the same input refined on an AVX2 and an AVX-512 host gives other figures for some sequences
(docs/method.md, "Benchmark figures are reproducible per CPU kind"). A result and a benchmark report therefore
name both, so a reader can tell whether two of them should agree bit for bit.
"""

from __future__ import annotations

import importlib
import platform
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def numpy_simd() -> str:
    """The SIMD extensions NumPy dispatches to on this CPU beyond its baseline (e.g. ``X86_V3 X86_V4``), or
    "baseline only"; two CPUs whose line differs may differ in NumPy's last bits."""
    try:
        umath = importlib.import_module("numpy._core._multiarray_umath")  # private, hence the guard
        found = [name for name in umath.__cpu_dispatch__ if umath.__cpu_features__.get(name)]
    except (ImportError, AttributeError):
        return "unknown"
    return " ".join(found) or "baseline only"
