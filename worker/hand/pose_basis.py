"""The packaged pose basis (DESIGN §1.3): a PCA over the built-in hand's 45 hinge angles.

``load_pose_basis()`` reads ``worker/hand/data/pose_basis.npz`` — ``mean`` (45,), ``components`` (n,45) orthonormal
rows ordered by variance, ``stddev`` (n,) per component (radians), ``explained_variance_ratio`` (n,) — and its
provenance (data, frames, date, git commit). Regenerate it with ``make pose-basis``
(``python -m worker.hand.pose_basis_build``). Controls use ``q = q_ref + components[:k].T @ (stddev[:k] * z)``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import ConfigurationError
from common.geometry import FloatArray

POSE_BASIS_FILE = Path(__file__).parent / "data" / "pose_basis.npz"


@dataclass(frozen=True)
class PoseBasis:
    """PCA of hinge angles: ``mean`` (45,), ``components`` (n,45), ``stddev`` (n,), ``explained_variance_ratio``."""

    mean: FloatArray
    components: FloatArray
    stddev: FloatArray
    explained_variance_ratio: FloatArray
    provenance: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.components.shape[0]
        if self.mean.shape != (45,) or self.components.shape != (n, 45) or self.stddev.shape != (n,):
            raise ValueError(
                f"PoseBasis: mean (45,), components (n,45), stddev (n,) expected; got {self.mean.shape}, "
                f"{self.components.shape}, {self.stddev.shape}"
            )

    def truncated(self, k: int) -> PoseBasis:
        """The first ``k`` components."""
        return PoseBasis(
            self.mean, self.components[:k], self.stddev[:k], self.explained_variance_ratio[:k], self.provenance
        )

    def to_hinges(self, coeffs: FloatArray) -> FloatArray:
        """Hinge offsets (...,45) for coefficients (...,k) in units of each component's standard deviation."""
        k = coeffs.shape[-1]
        return np.asarray((coeffs * self.stddev[:k]) @ self.components[:k])


def save_pose_basis(path: Path, basis: PoseBasis) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        path,
        mean=basis.mean,
        components=basis.components,
        stddev=basis.stddev,
        explained_variance_ratio=basis.explained_variance_ratio,
        provenance_json=np.array(json.dumps(basis.provenance, sort_keys=True)),
    )


@lru_cache(maxsize=4)
def load_pose_basis(path: Path = POSE_BASIS_FILE) -> PoseBasis:
    """The packaged (or given) basis; raises ``ConfigurationError`` when the file is missing."""
    if not path.is_file():
        raise ConfigurationError(f"pose basis {path} is missing; run `make pose-basis`")
    with np.load(path, allow_pickle=False) as data:
        return PoseBasis(
            mean=data["mean"],
            components=data["components"],
            stddev=data["stddev"],
            explained_variance_ratio=data["explained_variance_ratio"],
            provenance=json.loads(str(data["provenance_json"])),
        )


def fit_pose_basis(q: FloatArray, n_components: int = 20, provenance: dict[str, Any] | None = None) -> PoseBasis:
    """PCA (SVD of the centred data) of hinge-angle samples ``q`` (N,45)."""
    if q.ndim != 2 or q.shape[1] != 45 or q.shape[0] < 2:
        raise ValueError(f"q must have shape (N >= 2, 45), got {q.shape}")
    mean = q.mean(axis=0)
    _, s, vt = np.linalg.svd(q - mean, full_matrices=False)
    var = s**2 / (q.shape[0] - 1)
    n = min(n_components, vt.shape[0])
    return PoseBasis(
        mean=mean,
        components=vt[:n],
        stddev=np.sqrt(var[:n]),
        explained_variance_ratio=var[:n] / var.sum(),
        provenance=provenance or {},
    )
