"""Convex collision parts of an object mesh: CoACD decomposition, cached on disk by content hash (DESIGN §1.4).

MuJoCo collides meshes through their convex hulls, so a non-convex object (mug, bowl, clamp) needs a convex
decomposition. Meshes that are already (nearly) convex — volume at least ``CONVEX_VOLUME_RATIO`` of their
hull's — are used as one hull and never sent to CoACD. With a ``cache_dir`` (the entry points pass the configured
one) results are stored under ``cache_dir / "convex"`` keyed by a SHA-256 of the mesh bytes and the CoACD
parameters, so only the first run on a mesh pays for CoACD (0.5-10 s on the YCB meshes, 2 shared cores);
without one they are kept in memory for the process.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from common.geometry import FloatArray

#: Convex parts made in this process without a ``cache_dir``, by ``cache_key``, with how they were made: the
#: table fit and the scene build the same object, a refinement twice more for ``verify``.
_MEMO: dict[str, tuple[tuple[FloatArray, ...], str]] = {}

#: Quick CoACD settings (seconds, not minutes, on 300-800-vertex meshes), at most 16 parts.
COACD_PARAMS: dict[str, Any] = {
    "threshold": 0.08,
    "max_convex_hull": 16,
    "preprocess_mode": "off",
    "resolution": 1000,
    "mcts_iterations": 60,
    "mcts_nodes": 15,
    "mcts_max_depth": 2,
    "seed": 0,
}
#: CoACD settings by ``SimConfig.convex_detail``: the fine parts follow the surface twice as closely (half the
#: concavity threshold, up to twice the parts; CoACD takes a few times longer, once per mesh with a cache).
CONVEX_DETAIL_PARAMS: dict[str, dict[str, Any]] = {
    "coarse": COACD_PARAMS,
    "fine": {**COACD_PARAMS, "threshold": 0.04, "max_convex_hull": 32},
}
#: Mesh volume / hull volume above which the hull alone is used (cans and boxes: 0.90-0.98).
CONVEX_VOLUME_RATIO = 0.90
_CACHE_VERSION = 1


def cache_key(vertices: FloatArray, faces: npt.NDArray[np.int64], params: dict[str, Any] | None = None) -> str:
    """SHA-256 over the mesh bytes (float64 vertices, int64 faces) and the decomposition parameters."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(faces, dtype=np.int64).tobytes())
    h.update(json.dumps({"params": params or COACD_PARAMS, "ratio": CONVEX_VOLUME_RATIO, "v": _CACHE_VERSION}).encode())
    return h.hexdigest()


def _run_coacd(vertices: FloatArray, faces: npt.NDArray[np.int64], params: dict[str, Any]) -> list[FloatArray]:
    """Call CoACD; returns the vertices of each convex part (tests replace this to count calls)."""
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(coacd.Mesh(np.asarray(vertices), np.asarray(faces)), **params)
    return [np.asarray(p[0], dtype=np.float64) for p in parts]


def _hull_vertices(vertices: FloatArray) -> FloatArray:
    from scipy.spatial import ConvexHull

    return np.asarray(vertices[ConvexHull(vertices).vertices], dtype=np.float64)


def _decompose(
    vertices: FloatArray, faces: npt.NDArray[np.int64], params: dict[str, Any]
) -> tuple[list[FloatArray], str]:
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    if not mesh.is_watertight:
        # CoACD can crash the process (segfault) on non-manifold input; an open mesh gets its hull instead.
        return [_hull_vertices(vertices)], "hull"
    hull_volume = float(mesh.convex_hull.volume)
    if hull_volume > 0 and abs(float(mesh.volume)) / hull_volume >= CONVEX_VOLUME_RATIO:
        return [_hull_vertices(vertices)], "hull"
    parts = [p for p in _run_coacd(vertices, faces, params) if len(p) >= 4]
    if not parts:
        return [_hull_vertices(vertices)], "hull"
    return parts, "coacd"


def convex_parts(
    vertices: FloatArray,
    faces: npt.NDArray[np.int64],
    cache_dir: Path | None = None,
    params: dict[str, Any] | None = None,
) -> tuple[list[FloatArray], str]:
    """Convex parts of a mesh as vertex arrays (each (n_i,3), object frame) and how they were made
    (``"hull"``, ``"coacd"``, or ``"cache"`` when read back from ``cache_dir``). ``cache_dir`` None: memoised in
    this process only, nothing is written."""
    params = params or COACD_PARAMS
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {faces.shape}")
    key = cache_key(vertices, faces, params)
    if cache_dir is None:
        if key not in _MEMO:
            parts, how = _decompose(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), params)
            _MEMO[key] = (tuple(parts), how)
        memo_parts, memo_how = _MEMO[key]
        return list(memo_parts), memo_how
    folder = cache_dir / "convex"
    path = folder / f"{key}.npz"
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as data:
                offsets = data["offsets"]
                flat = data["vertices"]
                return [flat[offsets[i] : offsets[i + 1]] for i in range(len(offsets) - 1)], "cache"
        except (OSError, KeyError, ValueError):
            pass  # a corrupt cache entry is recomputed and overwritten
    parts, how = _decompose(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), params)
    folder.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    offsets = np.cumsum([0] + [len(p) for p in parts])
    np.savez(buf, vertices=np.concatenate(parts), offsets=offsets, method=np.array(how))
    # Write-then-rename: concurrent workers never read a half-written entry.
    fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
    with os.fdopen(fd, "wb") as fh:
        fh.write(buf.getvalue())
    os.replace(tmp, path)
    return parts, how
