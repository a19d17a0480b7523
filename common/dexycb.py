"""Reader for the DexYCB development NPZs (``shared/data/dexycb/dev/*.npz``, one sequence per file).

Those files name their object (``object_name``) but carry no mesh: the mesh and mass come from a YCB
folder (``<name>.obj`` + ``objects.json``) found, in order, from the ``ycb_dir`` argument,
``HOI_REFINE_YCB_DIR``, or ``<dexycb root>/../ycb`` next to the file. Poses stay in the camera frame;
``world_from_camera`` (gravity-aligned, table z = 0) is kept as the sequence's world transform.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Any, cast

import numpy as np

from common.errors import ConfigurationError, SequenceValidationError
from common.mesh_io import load_mesh_file
from common.npz_safe import SafeNpz, Spec
from common.safe_text import shown
from common.sequence import NUM_JOINTS, HandTrack, ManoParams, ObjectSpec, Sequence
from common.sequence_npz import ParseLimits, get_float, get_floats, get_str, open_npz
from common.settings import get_settings

DEXYCB_KEYS = ("fps", "side", "object_name", "hand_joints", "hand_valid", "object_pose", "world_from_camera")


def find_ycb_dir(near: Path | None = None, ycb_dir: Path | None = None) -> Path:
    candidates = [ycb_dir, get_settings().ycb_dir]
    if near is not None:
        # <data>/dexycb/dev/<file>.npz -> <data>/ycb
        candidates += [p / "ycb" for p in near.resolve().parents]
    for cand in candidates:
        if cand is not None and (Path(cand) / "objects.json").is_file():
            return Path(cand)
    raise ConfigurationError(
        "DexYCB files name their object but carry no mesh: set HOI_REFINE_YCB_DIR to a folder holding "
        "<object>.obj files and objects.json (e.g. shared/data/ycb)"
    )


@lru_cache(maxsize=64)
def _ycb_object(ycb_dir: Path, name: str) -> tuple[float, np.ndarray, np.ndarray]:
    table = json.loads((ycb_dir / "objects.json").read_text())
    if name not in table:
        # The message names the object only: the folder is this server's business, not the client's.
        raise SequenceValidationError.single("object_name", f"{shown(name)} is not a known YCB object")
    entry = table[name]
    vertices, faces = load_mesh_file(ycb_dir / entry.get("mesh", f"{name}.obj"), field="object_name")
    return float(entry["mass_kg"]), vertices, faces


def sequence_from_dexycb_npz(
    data: SafeNpz, max_frames: int | None = None, path: Path | None = None, ycb_dir: Path | None = None
) -> Sequence:
    """Build a validated ``Sequence`` from an open DexYCB development NPZ (see ``common.sequence_npz``)."""
    missing = [k for k in DEXYCB_KEYS if k not in data]
    if missing:
        raise SequenceValidationError.single(missing[0], "is missing from the DexYCB NPZ file")
    name = get_str(data, "object_name")
    side = get_str(data, "side")
    # Every member is checked before the YCB folder is looked at (or its absence reported).
    valid = data.get("hand_valid", Spec("b", ("T",)))
    keypoints = get_floats(data, "hand_joints", ("T", NUM_JOINTS, 3))
    pose = get_floats(data, "object_pose", ("T", 7))
    world = get_floats(data, "world_from_camera", (4, 4))
    fps = get_float(data, "fps")
    mano = None
    if "mano_pose_pca" in data and "mano_trans" in data and "mano_betas" in data:
        pose_pca = get_floats(data, "mano_pose_pca", ("T", 48))
        mano = ManoParams(
            global_orient=pose_pca[:, :3],
            hand_pose=pose_pca[:, 3:],
            trans=get_floats(data, "mano_trans", ("T", 3)),
            betas=get_floats(data, "mano_betas", ("B",)),
            pose_format="pca",
            flat_hand_mean=False,
        )
    subject = get_str(data, "subject") if "subject" in data else "unknown"
    sequence = get_str(data, "sequence") if "sequence" in data else (path.stem if path else "sequence")
    mass, vertices, faces = _ycb_object(find_ycb_dir(path, ycb_dir), name)
    seq = Sequence(
        name=f"{subject}__{sequence}",
        fps=fps,
        object=ObjectSpec(name=name, mass_kg=mass, mesh_vertices=vertices.copy(), mesh_faces=faces.copy()),
        object_pose=pose,
        hands=[HandTrack(side=cast(Any, side), valid=valid, keypoints=keypoints, mano=mano)],
        world_from_source=world,
        meta={"source": "dexycb-dev", "subject": subject, "sequence": sequence},
    )
    if path is not None:
        seq.meta["source_path"] = str(path)
    return seq.validate(max_frames=max_frames)


def load_dexycb_npz(path: Path | str, ycb_dir: Path | None = None, max_frames: int | None = None) -> Sequence:
    path = Path(path)
    limits = ParseLimits() if max_frames is None else ParseLimits(max_frames=max_frames)
    with open_npz(path.read_bytes(), limits) as data:
        return sequence_from_dexycb_npz(data, max_frames=max_frames, path=path, ycb_dir=ycb_dir)


def shared_data_dir() -> Path | None:
    """``../shared/data`` beside the checkout, or ``HOI_REFINE_SHARED_DATA``; None when absent."""
    import os

    env = os.environ.get("HOI_REFINE_SHARED_DATA")
    cands = [Path(env)] if env else []
    cands.append(Path(__file__).resolve().parents[2] / "shared" / "data")
    return next((c for c in cands if (c / "dexycb").is_dir()), None)
