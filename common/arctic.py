"""ARCTIC recordings (two hands, an articulated object) as sequences (issue #52 item 5).

Two layouts are read, both from local files:

* **dexmachina-processed** (``<assets>/arctic/processed/<subject>/<object>_use_NN.npy``, a pickled dict per
  sequence, read by ``common.safe_pickle``): ``world_coord["joints.right" | "joints.left"]`` (T, 21, 3) world
  joints in MANO's order (wrist, index, middle, pinky, ring, thumb three each, then the five tips), and
  ``params`` with ``obj_trans`` (T, 3) metres, ``obj_quat`` (T, 4) wxyz and ``obj_arti`` (T,) radians. The object
  is the URDF beside it (``<assets>/arctic/<object>/<object>.urdf``, ``common.urdf_object``), or under
  ``object_dir``. No MANO model is needed.
* the **ARCTIC release** (``raw_seqs/<subject>/<seq>.mano.npy`` + ``.object.npy``, templates under
  ``meta/object_vtemplates/<object>/``): ``common.arctic_release``.

ARCTIC's world is z-up with the table a little under the objects (about 0.95 m up); ``up`` = +z lets the sequence
put the table under the frame-0 object. ARCTIC's frames are its videos' 30 per second (the project's own viewer and
evaluation code, ``common/viewer.py`` and ``src/utils/eval_modules.py`` in zc-alexfan/arctic, play and
differentiate them at 30).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from common.errors import UnsupportedFormatError
from common.safe_pickle import load_object_npy
from common.sequence import HandTrack, ObjectSpec, Sequence
from common.urdf_object import object_from_urdf

ARCTIC_FPS = 30.0
#: MANO's joint order (16 joints, then the tips thumb, index, middle, ring, pinky) -> ``common.sequence.JOINT_NAMES``.
MANO_TO_OPENPOSE = (0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20)


def is_dexmachina_processed(path: Path) -> bool:
    """A ``.npy`` that is not part of an ARCTIC release sequence (``*.mano.npy`` / ``*.object.npy`` ...)."""
    return path.suffix.lower() == ".npy" and len(path.suffixes) == 1


def object_name_of(path: Path) -> str:
    """``laptop`` from ``laptop_use_01.npy`` / ``laptop_grab_01.mano.npy``."""
    stem = path.name.split(".")[0]
    for marker in ("_use_", "_grab_"):
        if marker in stem:
            return stem.split(marker)[0]
    return stem.rsplit("_", 1)[0]


def _get(d: Any, *keys: str, where: str) -> Any:
    for key in keys:
        if not isinstance(d, dict) or key not in d:
            raise UnsupportedFormatError(f"{where}: missing {'.'.join(keys)}")
        d = d[key]
    return d


def _array(value: Any, shape: tuple[int | None, ...], where: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "iuf" or arr.ndim != len(shape) or any(
            s is not None and s != a for s, a in zip(shape, arr.shape, strict=True)):
        raise UnsupportedFormatError(f"{where}: expected shape {shape} of numbers, got {arr.shape} {arr.dtype}")
    return np.asarray(arr, dtype=np.float64)


def widen_limits(obj: ObjectSpec, articulation: np.ndarray) -> dict[str, str]:
    """Joint limits widened to the recorded values where the recording passes them (a waffle iron recorded at
    2.84 rad against its URDF's 2.8): the recording is what is refined; ``meta`` entries say what changed."""
    notes = {}
    for k, joint in enumerate(obj.joints):
        lo, hi = float(joint.limits[0]), float(joint.limits[1])
        new_lo, new_hi = min(lo, float(articulation[:, k].min())), max(hi, float(articulation[:, k].max()))
        if (new_lo, new_hi) != (lo, hi):
            joint.limits = np.array([new_lo, new_hi])
            notes[f"limits_widened.{joint.name}"] = f"[{lo:g}, {hi:g}] -> [{new_lo:.6g}, {new_hi:.6g}]"
    return notes


def load_arctic(path: Path, object_dir: Path | None = None, max_frames: int | None = None) -> Sequence:
    """Either ARCTIC layout (module docstring), by the file's name."""
    if is_dexmachina_processed(path):
        return load_dexmachina_processed(path, object_dir, max_frames)
    from common.arctic_release import load_arctic_release

    return load_arctic_release(path, object_dir, max_frames)


def load_dexmachina_processed(path: Path, object_dir: Path | None = None, max_frames: int | None = None) -> Sequence:
    """A dexmachina-processed ARCTIC sequence and its object (see the module docstring)."""
    data = load_object_npy(path)
    where = path.name
    obj_name = object_name_of(path)
    folder = object_dir if object_dir is not None else path.resolve().parents[2] / obj_name
    urdf = folder / f"{obj_name}.urdf"
    if not urdf.is_file():
        raise UnsupportedFormatError(f"{where}: no object URDF at {urdf} (give the object's folder: --object-dir)")
    obj = object_from_urdf(urdf, name=obj_name)
    params = _get(data, "params", where=where)
    trans = _array(_get(params, "obj_trans", where=where), (None, 3), f"{where} params.obj_trans")
    t = len(trans)
    quat = _array(_get(params, "obj_quat", where=where), (t, 4), f"{where} params.obj_quat")
    arti = _array(_get(params, "obj_arti", where=where), (t,), f"{where} params.obj_arti")
    meta = {"source": "arctic (dexmachina-processed)", "subject": path.parent.name, "object": obj_name}
    meta.update(widen_limits(obj, arti[:, None]))
    hands = []
    for side in ("right", "left"):
        joints = _array(_get(data, "world_coord", f"joints.{side}", where=where), (t, 21, 3),
                        f"{where} world_coord.joints.{side}")  # fmt: skip
        keypoints = joints[:, list(MANO_TO_OPENPOSE)]
        hands.append(HandTrack(side=side, valid=np.isfinite(keypoints).all(axis=(1, 2)), keypoints=keypoints))
    seq = Sequence(
        name=path.stem, fps=ARCTIC_FPS, object=obj, object_pose=np.concatenate([trans, quat], axis=1), hands=hands,
        up=np.array([0.0, 0.0, 1.0]), articulation=arti[:, None].copy(), meta=meta,
    )  # fmt: skip
    return seq.validate(max_frames=max_frames)
