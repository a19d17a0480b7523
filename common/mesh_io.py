"""Mesh files (OBJ/PLY/STL/GLB/GLTF/OFF) read into (vertices, faces) arrays.

Its own module, below every sequence format: the native JSON format (``common.sequence_io``) and both DexYCB
readers (``common.dexycb``, ``common.dexycb_native``) load object meshes through it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np
import trimesh

from common.errors import SequenceValidationError

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")


def load_mesh_file(path: Path, field: str = "object.mesh_file") -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh (vertices, faces) with trimesh; scenes are merged into one mesh."""
    # Messages name the file, not its folder: a DexYCB upload's mesh lives on the server (issue #16).
    if not path.is_file():
        raise SequenceValidationError.single(field, f"mesh file {path.name} does not exist")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise SequenceValidationError.single(
            field, f"unsupported mesh type {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}"
        )
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise SequenceValidationError.single(field, f"could not read mesh {path.name} ({type(exc).__name__})") from exc
    mesh = cast(Any, loaded)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if vertices.size == 0 or faces.size == 0:
        raise SequenceValidationError.single(field, f"mesh {path.name} is empty")
    return vertices, faces
