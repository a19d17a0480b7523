"""A small, well-formed MANO-format model file for tests and demos (the real MANO files are licensed).

``build_test_mano_model`` writes a pickle with every key of the released ``MANO_*.pkl`` files, built from a
hand skeleton: 16 joints in MANO order, a ring of vertices around every joint and along every bone, palm
vertices, skinning weights from the bone each vertex surrounds, a J_regressor that averages each joint's
ring (so regressed joints are exact), linear shape directions (beta 0 = overall size, beta 1 = finger length)
and small pose correctives. Like the real files it holds ``chumpy.ch.Ch`` objects (a throw-away stand-in
class registered only while pickling) and a scipy sparse J_regressor, so the no-chumpy loader is exercised.
Fingertip vertex ids (the real model uses 745, 317, 444, 556, 673) are stored under ``tip_vertex_ids``.
"""

from __future__ import annotations

import pickle
import sys
import types
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from common.sequence import Side

#: MANO's kinematic tree: parent of joints 1..15 (0 wrist; index 1-3, middle 4-6, pinky 7-9, ring 10-12,
#: thumb 13-15).
MANO_PARENTS: tuple[int, ...] = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14)
#: First MANO joint of each finger in MANO21 finger order (thumb, index, middle, ring, pinky).
MANO_FINGER_START: tuple[int, ...] = (13, 1, 4, 10, 7)
RING = 8

# Right-hand skeleton (metres; palm faces +z, fingers along +x, thumb towards -y), MANO21 finger order.
_BASES = np.array([[0.030, -0.024, 0.008], [0.090, -0.024, 0.0], [0.093, 0.0, 0.0], [0.086, 0.019, 0.002],
                   [0.077, 0.036, 0.0]])  # fmt: skip
_LENGTHS = np.array([[0.040, 0.032, 0.028], [0.042, 0.025, 0.022], [0.046, 0.028, 0.024],
                     [0.043, 0.027, 0.023], [0.034, 0.020, 0.021]])  # fmt: skip
_RADII = np.array([0.011, 0.0095, 0.0095, 0.009, 0.008])
_THUMB_DIR = np.array([0.70, -0.60, 0.38])
_WRIST = np.array([0.012, 0.004, -0.003])  # not at the origin, like the real template: rotations are about J0


def skeleton() -> tuple[np.ndarray, np.ndarray]:
    """(16,3) joints in MANO order and (5,3) fingertips (MANO21 finger order) of the right template hand."""
    joints = np.zeros((16, 3))
    tips = np.zeros((5, 3))
    joints[0] = _WRIST
    for f, start in enumerate(MANO_FINGER_START):
        direction = _THUMB_DIR / np.linalg.norm(_THUMB_DIR) if f == 0 else np.array([1.0, 0.0, 0.0])
        bend = Rotation.from_rotvec(np.radians(6.0) * np.array([0.0, -1.0, 0.0]))  # slight rest curl
        pos = _WRIST + _BASES[f]
        for j in range(3):
            joints[start + j] = pos
            pos = pos + _LENGTHS[f, j] * direction
            direction = bend.apply(direction)
        tips[f] = pos
    return joints, tips


def _ring(center: np.ndarray, axis: np.ndarray, radius: float, flat: float = 1.0) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    u = np.cross(axis, [0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.cross(axis, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    ang = np.linspace(0, 2 * np.pi, RING, endpoint=False)
    return center + radius * (np.cos(ang)[:, None] * u + flat * np.sin(ang)[:, None] * v)


def _geometry() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """Vertices, weights (V,16), J_regressor (16,V), faces, tip vertex ids of the right template hand."""
    joints, tips = skeleton()
    verts: list[np.ndarray] = []
    weights: list[np.ndarray] = []
    parts: list[list[int]] = [[] for _ in range(16)]
    regressor = np.zeros((16, 0))
    strips: list[tuple[list[int], list[int]]] = []

    def add(points: np.ndarray, w: dict[int, float], part: int) -> list[int]:
        start = sum(len(v) for v in verts)
        ids = list(range(start, start + len(points)))
        verts.append(points)
        row = np.zeros((len(points), 16))
        for j, val in w.items():
            row[:, j] = val
        weights.append(row)
        parts[part].extend(ids)
        return ids

    joint_rings: dict[int, list[int]] = {0: add(_ring(_WRIST, np.array([1.0, 0, 0]), 0.028, 0.45), {0: 1.0}, 0)}
    for x in (0.035, 0.065):  # palm body between wrist and knuckles
        add(_ring(_WRIST + np.array([x, 0.006, 0.0]), np.array([1.0, 0, 0]), 0.04, 0.35), {0: 1.0}, 0)
    tip_ids = []
    for f, start in enumerate(MANO_FINGER_START):
        chain = [*range(start, start + 3)]
        ends = [*joints[chain[1:]], tips[f]]
        prev_ring: list[int] | None = None
        for j, jid in enumerate(chain):
            axis = ends[j] - joints[jid]
            parent = MANO_PARENTS[jid]
            r = _RADII[f] * (1.0 - 0.1 * j)
            ring = add(_ring(joints[jid], axis, r), {jid: 0.6, parent: 0.4}, jid)
            joint_rings[jid] = ring
            if prev_ring is not None:
                strips.append((prev_ring, ring))
            # Most of a bone's skin follows that bone alone (the distal one tapers towards the tip).
            mid = add(_ring(joints[jid] + 0.5 * axis, axis, r), {jid: 1.0}, jid)
            end = add(_ring(joints[jid] + 0.85 * axis, axis, r * (0.7 if j == 2 else 1.0)), {jid: 1.0}, jid)
            strips += [(ring, mid), (mid, end)]
            prev_ring = end
        assert prev_ring is not None
        tip = add(tips[f][None], {chain[-1]: 1.0}, chain[-1])
        tip_ids.append(tip[0])
        strips.append((prev_ring, tip * RING))
    v = np.concatenate(verts)
    w = np.concatenate(weights)
    regressor = np.zeros((16, len(v)))
    for j, ids in joint_rings.items():
        regressor[j, ids] = 1.0 / len(ids)
    faces: list[tuple[int, int, int]] = []
    for a, b in strips:
        for k in range(RING):
            k2 = (k + 1) % RING
            faces += [(a[k], a[k2], b[k]), (b[k], a[k2], b[k2])] if len(set(b)) > 1 else [(a[k], a[k2], b[0])]
    palm = np.array(parts[0])
    faces += [tuple(int(i) for i in palm[s]) for s in ConvexHull(v[palm]).simplices]  # type: ignore[misc]
    return v, w, regressor, np.array(faces, dtype=np.uint32), tip_ids


def _fake_chumpy() -> tuple[type, dict[str, Any]]:
    """A class that pickles as ``chumpy.ch.Ch`` with state ``{'x': array}``, and the sys.modules entries."""
    module = types.ModuleType("chumpy.ch")

    class Ch:
        def __init__(self, x: np.ndarray) -> None:
            self.x = x

    Ch.__module__, Ch.__qualname__, Ch.__name__ = "chumpy.ch", "Ch", "Ch"
    module.Ch = Ch  # type: ignore[attr-defined]
    package = types.ModuleType("chumpy")
    package.ch = module  # type: ignore[attr-defined]
    return Ch, {"chumpy": package, "chumpy.ch": module}


def build_test_mano_model(path: Path | str, side: Side = "right", seed: int = 0) -> Path:
    """Write a MANO-format pickle for ``side`` to ``path`` (a file, or a folder -> ``MANO_<SIDE>.pkl``)."""
    path = Path(path)
    if path.is_dir():
        path = path / f"MANO_{side.upper()}.pkl"
    rng = np.random.default_rng(seed)
    v, w, regressor, faces, tip_ids = _geometry()
    centred = v - _WRIST
    shapedirs = np.zeros((len(v), 3, 10))
    shapedirs[:, :, 0] = 0.04 * centred  # overall size
    shapedirs[:, :, 1] = 0.04 * centred * [1.0, 0.0, 0.0]  # finger length
    for k in range(2, 10):  # small smooth (linear) shape changes
        shapedirs[:, :, k] = 0.005 * centred @ rng.normal(size=(3, 3)).T
    posedirs = 1e-4 * rng.normal(size=(len(v), 3, 135))
    components = np.linalg.qr(rng.normal(size=(45, 45)))[0].T  # orthonormal rows, like MANO's PCA
    hands_mean = 0.15 * rng.normal(size=45)
    if side == "left":  # the left model mirrors the right one
        v, shapedirs, posedirs = v * [1, -1, 1], shapedirs * [[1], [-1], [1]], posedirs * [[1], [-1], [1]]
        faces = faces[:, ::-1].copy()
    kintree = np.array([[2**32 - 1, *MANO_PARENTS[1:]], list(range(16))], dtype=np.uint32)
    ch, modules = _fake_chumpy()
    data = {
        "v_template": ch(v),
        "shapedirs": ch(shapedirs),
        "J": ch(regressor @ v),
        "posedirs": posedirs,
        "J_regressor": scipy.sparse.csc_matrix(regressor),
        "weights": ch(w),
        "kintree_table": kintree,
        "f": faces,
        "hands_components": components,
        "hands_mean": hands_mean,
        "hands_coeffs": rng.normal(size=(20, 45)),
        "bs_style": "lbs",
        "bs_type": "lrotmin",
        "tip_vertex_ids": np.array(tip_ids, dtype=np.int64),
    }
    saved = {name: sys.modules.get(name) for name in modules}
    sys.modules.update(modules)
    try:
        with path.open("wb") as fh:
            pickle.dump(data, fh, protocol=2)
    finally:
        for name, old in saved.items():
            if old is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = old
    return path
