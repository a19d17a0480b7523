"""Convex decomposition: non-convex meshes go through CoACD once, then come from the content-hashed cache."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from worker.simulation import convex_cache


def _ring() -> trimesh.Trimesh:
    """A watertight, clearly non-convex mesh (a flat ring: 67% of its hull's volume), 64 vertices."""
    return trimesh.creation.annulus(r_min=0.02, r_max=0.035, height=0.02, sections=16)


def test_non_convex_mesh_is_decomposed_once_then_cached(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    mesh = _ring()
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64)
    calls: list[int] = []
    real = convex_cache._run_coacd

    def counting(*args: object, **kwargs: object) -> list[np.ndarray]:
        calls.append(1)
        return real(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(convex_cache, "_run_coacd", counting)
    parts, how = convex_cache.convex_parts(vertices, faces, cache_dir=tmp_path)
    assert how == "coacd" and len(calls) == 1
    assert 2 <= len(parts) <= convex_cache.COACD_PARAMS["max_convex_hull"]
    # The parts cover the ring: together they span its bounding box.
    lo = np.min([p.min(axis=0) for p in parts], axis=0)
    hi = np.max([p.max(axis=0) for p in parts], axis=0)
    np.testing.assert_allclose(lo, vertices.min(axis=0), atol=5e-3)
    np.testing.assert_allclose(hi, vertices.max(axis=0), atol=5e-3)

    again, how2 = convex_cache.convex_parts(vertices, faces, cache_dir=tmp_path)
    assert how2 == "cache" and len(calls) == 1  # second load does not call CoACD
    assert len(again) == len(parts) and all(np.array_equal(a, b) for a, b in zip(again, parts, strict=True))

    moved = vertices + np.array([0.001, 0.0, 0.0])  # different bytes -> different key -> recomputed
    convex_cache.convex_parts(moved, faces, cache_dir=tmp_path)
    assert len(calls) == 2


def test_convex_mesh_skips_coacd(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def forbidden(*args: object, **kwargs: object) -> list[np.ndarray]:
        raise AssertionError("CoACD must not run on a convex mesh")

    monkeypatch.setattr(convex_cache, "_run_coacd", forbidden)
    box = trimesh.creation.box(extents=[0.05, 0.04, 0.1])
    parts, how = convex_cache.convex_parts(np.asarray(box.vertices), np.asarray(box.faces), cache_dir=tmp_path)
    assert how == "hull" and len(parts) == 1 and len(parts[0]) == 8


def test_without_cache_dir_nothing_is_written_and_the_process_remembers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Science code reads no settings: without a ``cache_dir`` the parts stay in this process's memory."""
    monkeypatch.chdir(tmp_path)
    ring = _ring()
    vertices, faces = np.asarray(ring.vertices) * 1.01, np.asarray(ring.faces)  # a key no other test used
    calls: list[int] = []
    real = convex_cache._run_coacd

    def counting(*args: Any, **kwargs: Any) -> list[np.ndarray]:
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(convex_cache, "_run_coacd", counting)
    parts, how = convex_cache.convex_parts(vertices, faces)
    again, how2 = convex_cache.convex_parts(vertices, faces)
    assert how == how2 == "coacd" and len(calls) == 1
    assert all(np.array_equal(a, b) for a, b in zip(again, parts, strict=True))
    assert not list(tmp_path.rglob("*.npz")) and not (tmp_path / "var").exists()


def test_shape_checks_name_the_argument() -> None:
    with pytest.raises(ValueError, match="vertices"):
        convex_cache.convex_parts(np.zeros((4, 2)), np.zeros((4, 3), dtype=np.int64))


def test_open_mesh_gets_its_hull_not_coacd(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def forbidden(*args: object, **kwargs: object) -> list[np.ndarray]:
        raise AssertionError("CoACD must not see a non-watertight mesh (it can segfault)")

    monkeypatch.setattr(convex_cache, "_run_coacd", forbidden)
    ring = _ring()
    faces = np.asarray(ring.faces)[:-4]  # punch a hole
    parts, how = convex_cache.convex_parts(np.asarray(ring.vertices), faces, cache_dir=tmp_path)
    assert how == "hull" and len(parts) == 1
