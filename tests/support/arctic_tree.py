"""Small ARCTIC trees written by the tests themselves (the real files may not be copied, issue #52): the release
layout (``raw_seqs`` + ``meta/object_vtemplates``) and the dexmachina-processed layout (a pickled ``.npy`` per
sequence + the object's URDF and meshes)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

T = 3
#: The object's frames: articulation angle (rad), axis-angle rotation, translation (mm).
ANGLES = np.array([0.0, 0.3, 0.6])
ROTVECS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.1], [0.1, -0.05, 0.0]])
TRANS_MM = np.array([[100.0, 200.0, 950.0], [102.0, 199.0, 951.0], [104.0, 198.0, 953.0]])
#: The template: a 100 x 80 x 30 mm bottom box under a 100 x 80 x 10 mm top box (millimetres, object frame).
BOTTOM_MM = ((0.0, 100.0), (-40.0, 40.0), (0.0, 30.0))
TOP_MM = ((0.0, 100.0), (-40.0, 40.0), (30.0, 40.0))


def box_obj(bounds: tuple[tuple[float, float], ...], offset: int = 0) -> tuple[list[str], list[str]]:
    """OBJ ``v`` and ``f`` lines of an axis-aligned box (outward faces), vertex indices from ``offset`` + 1."""
    (x0, x1), (y0, y1), (z0, z1) = bounds
    verts = [f"v {x} {y} {z}" for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)]
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]  # fmt: skip
    return verts, [f"f {a + 1 + offset} {b + 1 + offset} {c + 1 + offset}" for a, b, c in faces]


def mano_hand(rng: np.random.Generator, per_frame_shape: bool) -> dict[str, np.ndarray]:
    shape = rng.normal(0, 0.5, 10)
    return {
        "rot": rng.normal(0, 0.5, (T, 3)), "pose": rng.normal(0, 0.2, (T, 45)),
        "trans": np.array([0.1, 0.2, 1.0]) + rng.normal(0, 0.02, (T, 3)),
        "shape": np.tile(shape, (T, 1)) if per_frame_shape else shape, "fitting_err": np.full(T, 1e-3),
    }  # fmt: skip


def write_release_tree(root: Path, split_meshes: bool = False, seed: int = 0) -> Path:
    """``root/raw_seqs/s01/box_grab_01.{mano,object}.npy`` and ``root/meta/object_vtemplates/box/`` (``mesh.obj`` +
    ``parts.json``, or ``top.obj`` + ``bottom.obj`` with ``split_meshes``); returns the ``.mano.npy`` path."""
    rng = np.random.default_rng(seed)
    seqs = root / "raw_seqs" / "s01"
    seqs.mkdir(parents=True)
    mano = {"right": mano_hand(rng, per_frame_shape=False), "left": mano_hand(rng, per_frame_shape=True)}
    np.save(seqs / "box_grab_01.mano.npy", mano, allow_pickle=True)  # type: ignore[arg-type]
    np.save(seqs / "box_grab_01.object.npy", np.concatenate([ANGLES[:, None], ROTVECS, TRANS_MM], axis=1))
    template = root / "meta" / "object_vtemplates" / "box"
    template.mkdir(parents=True)
    bv, bf = box_obj(BOTTOM_MM)
    if split_meshes:
        tv, tf = box_obj(TOP_MM)
        (template / "bottom.obj").write_text("\n".join(bv + bf) + "\n")
        (template / "top.obj").write_text("\n".join(tv + tf) + "\n")
    else:
        tv, tf = box_obj(TOP_MM, offset=8)
        (template / "mesh.obj").write_text("\n".join(bv + tv + bf + tf) + "\n")
        (template / "parts.json").write_text(json.dumps([0] * 8 + [1] * 8))
    return seqs / "box_grab_01.mano.npy"


#: The dexmachina-processed object: the URDF's base and lid (metres), the lid hinged about -z at its origin.
DEX_URDF = """<?xml version="1.0" ?>
<robot name="box">
  <link name="top">
    <inertial><mass value="0.15"/></inertial>
    <collision><origin xyz="0 0 0" rpy="0 0 0"/><geometry><mesh filename="top.obj" scale="0.001 0.001 0.001"/>
    </geometry></collision>
  </link>
  <link name="bottom">
    <inertial><mass value="0.9"/></inertial>
    <collision><geometry><mesh filename="bottom.obj" scale="0.001 0.001 0.001"/></geometry></collision>
  </link>
  <joint name="rotation" type="revolute">
    <origin xyz="0 0 0"/>
    <axis xyz="0 0 -1"/>
    <parent link="bottom"/>
    <child link="top"/>
    <limit lower="0" upper="0.5"/>
  </joint>
</robot>
"""


def write_dexmachina_tree(root: Path, seed: int = 0) -> tuple[Path, dict[str, np.ndarray]]:
    """``root/arctic/processed/s01/box_use_01.npy`` (pickled dict) and ``root/arctic/box/box.urdf`` with its OBJ
    meshes (millimetres, scaled by the URDF); returns the sequence path and the joints written per side (MANO
    order, world)."""
    rng = np.random.default_rng(seed)
    obj_dir = root / "arctic" / "box"
    obj_dir.mkdir(parents=True)
    for name, bounds in (("bottom", BOTTOM_MM), ("top", TOP_MM)):
        v, f = box_obj(bounds)
        (obj_dir / f"{name}.obj").write_text("\n".join(v + f) + "\n")
    (obj_dir / "box.urdf").write_text(DEX_URDF)
    seq_dir = root / "arctic" / "processed" / "s01"
    seq_dir.mkdir(parents=True)
    joints = {side: np.array([0.1, 0.2, 1.0]) + rng.normal(0, 0.05, (T, 21, 3)) for side in ("right", "left")}
    from scipy.spatial.transform import Rotation

    data = {
        "world_coord": {f"joints.{side}": j for side, j in joints.items()},
        "params": {"obj_trans": TRANS_MM / 1000.0, "obj_quat": Rotation.from_rotvec(ROTVECS).as_quat(scalar_first=True),
                   "obj_arti": ANGLES.copy()},
    }  # fmt: skip
    path = seq_dir / "box_use_01.npy"
    np.save(path, data, allow_pickle=True)  # type: ignore[arg-type]
    return path, joints

