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
from common.sequence import HandTrack, ManoParams, ObjectSpec, Sequence
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
        raise SequenceValidationError.single("object_name", f"{name!r} is not in {ycb_dir / 'objects.json'}")
    entry = table[name]
    vertices, faces = load_mesh_file(ycb_dir / entry.get("mesh", f"{name}.obj"), field="object_name")
    return float(entry["mass_kg"]), vertices, faces


def sequence_from_dexycb_npz(
    data: Any, max_frames: int | None = None, path: Path | None = None, ycb_dir: Path | None = None
) -> Sequence:
    """Build a validated ``Sequence`` from an open DexYCB development NPZ."""
    missing = [k for k in DEXYCB_KEYS if k not in data.files]
    if missing:
        raise SequenceValidationError.single(missing[0], "is missing from the DexYCB NPZ file")
    name = str(data["object_name"])
    mass, vertices, faces = _ycb_object(find_ycb_dir(path, ycb_dir), name)
    pose_pca = np.asarray(data["mano_pose_pca"], dtype=np.float64) if "mano_pose_pca" in data.files else None
    valid = np.asarray(data["hand_valid"], dtype=bool)
    hand = HandTrack(
        side=cast(Any, str(data["side"])),
        valid=valid,
        keypoints=np.asarray(data["hand_joints"], dtype=np.float64),
    )
    if pose_pca is not None and "mano_trans" in data.files:
        hand.mano = ManoParams(
            global_orient=pose_pca[:, :3],
            hand_pose=pose_pca[:, 3:],
            trans=np.asarray(data["mano_trans"], dtype=np.float64),
            betas=np.asarray(data["mano_betas"], dtype=np.float64),
            pose_format="pca",
            flat_hand_mean=False,
        )
    subject = str(data["subject"]) if "subject" in data.files else "unknown"
    sequence = str(data["sequence"]) if "sequence" in data.files else (path.stem if path else "sequence")
    seq = Sequence(
        name=f"{subject}__{sequence}",
        fps=float(data["fps"]),
        object=ObjectSpec(name=name, mass_kg=mass, mesh_vertices=vertices.copy(), mesh_faces=faces.copy()),
        object_pose=np.asarray(data["object_pose"], dtype=np.float64),
        hands=[hand],
        world_from_source=np.asarray(data["world_from_camera"], dtype=np.float64),
        meta={"source": "dexycb-dev", "subject": subject, "sequence": sequence},
    )
    if path is not None:
        seq.meta["source_path"] = str(path)
    return seq.validate(max_frames=max_frames)


def load_dexycb_npz(path: Path | str, ycb_dir: Path | None = None, max_frames: int | None = None) -> Sequence:
    path = Path(path)
    with np.load(path, allow_pickle=False) as data:
        return sequence_from_dexycb_npz(data, max_frames=max_frames, path=path, ycb_dir=ycb_dir)


def shared_data_dir() -> Path | None:
    """``../shared/data`` beside the checkout, or ``HOI_REFINE_SHARED_DATA``; None when absent."""
    import os

    env = os.environ.get("HOI_REFINE_SHARED_DATA")
    cands = [Path(env)] if env else []
    cands.append(Path(__file__).resolve().parents[2] / "shared" / "data")
    return next((c for c in cands if (c / "dexycb").is_dir()), None)
