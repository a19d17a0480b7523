"""MANO parameters -> keypoints, per-joint rotations and vertices, through ``smplx`` (optional extra ``mano``).

torch and smplx are imported lazily (``pip install .[mano]``); the rest of the project never needs them.
The smplx layer is built from the no-chumpy dict (``data_struct``), so the licensed pickle is never rewritten.
PCA inputs are turned into axis-angle here (``coeffs @ hands_components[:n]``) and the hand mean is added
here unless ``flat_hand_mean``: smplx silently treats ``num_pca_comps == 45`` as axis-angle, and DexYCB's
convention is exactly 45 PCA coefficients with the mean added (manopth ``use_pca=True, flat_hand_mean=False``).
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from common.errors import ConfigurationError, SequenceValidationError
from common.geometry import FloatArray
from common.sequence import ManoParams, Side
from worker.hand.mano.pickle_io import load_mano_pickle, mano_model_path

#: Fingertip vertices of the real MANO mesh (thumb, index, middle, ring, pinky), as in manopth / DexYCB.
MANO_TIP_VERTEX_IDS: tuple[int, ...] = (745, 317, 444, 556, 673)
#: Rows of [16 MANO joints, 5 tips] giving MANO21/OpenPose order (``common.sequence.JOINT_NAMES``).
MANO21_ORDER: tuple[int, ...] = (0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20)


@dataclass(frozen=True, eq=False)  # hashed by identity: one smplx layer per loaded file
class ManoModel:
    """A MANO model file read into NumPy (``data`` holds every key of the pickle)."""

    path: Path
    side: Side
    data: dict[str, Any]

    @property
    def tip_vertex_ids(self) -> tuple[int, ...]:
        if "tip_vertex_ids" in self.data:  # test models carry their own
            return tuple(int(i) for i in self.data["tip_vertex_ids"])
        n = int(np.asarray(self.data["v_template"]).shape[0])
        if n != 778:
            raise ConfigurationError(f"{self.path}: {n} vertices and no tip_vertex_ids; cannot place fingertips")
        return MANO_TIP_VERTEX_IDS

    @property
    def hands_components(self) -> FloatArray:
        return np.asarray(self.data["hands_components"], dtype=np.float64)

    @property
    def hands_mean(self) -> FloatArray:
        return np.asarray(self.data["hands_mean"], dtype=np.float64).reshape(45)


@lru_cache(maxsize=4)
def _load_model(path: Path, mtime: float, side: Side) -> ManoModel:
    return ManoModel(path=path, side=side, data=load_mano_pickle(path))


def load_mano_model(side: Side, mano_dir: Path | str | None = None) -> ManoModel:
    """The model for ``side`` from ``mano_dir`` or ``HOI_REFINE_MANO_DIR`` (cached; clear error if absent)."""
    path = mano_model_path(side, mano_dir).resolve()
    return _load_model(path, path.stat().st_mtime, side)


@lru_cache(maxsize=4)
def _smplx_layer(model: ManoModel) -> Any:
    try:
        import torch
        from smplx import MANO
        from smplx.utils import Struct
    except ImportError as exc:  # pragma: no cover - depends on the installed extras
        raise ConfigurationError(
            f"decoding MANO parameters needs torch and smplx: pip install 'hoi-refine[mano]' ({exc})"
        ) from exc
    # smplx prints a warning about having only 10 shape coefficients; that is MANO's normal size.
    with contextlib.redirect_stdout(io.StringIO()):
        layer = MANO(
            model_path=str(model.path), is_rhand=model.side == "right", data_struct=Struct(**model.data),
            use_pca=False, flat_hand_mean=True, num_pca_comps=45, dtype=torch.float64, batch_size=1,
        )  # fmt: skip
    return layer.eval()


def full_hand_pose(params: ManoParams, model: ManoModel) -> FloatArray:
    """(T, 45) axis-angle finger pose with the hand mean included (the pose smplx's LBS applies)."""
    pose = np.asarray(params.hand_pose, dtype=np.float64)
    if pose.ndim != 2:
        raise SequenceValidationError.single("mano.hand_pose", f"must be (T, n), got shape {pose.shape}")
    if params.pose_format == "pca":
        n = pose.shape[1]
        if not 1 <= n <= model.hands_components.shape[0]:
            raise SequenceValidationError.single("mano.hand_pose", f"PCA needs 1-45 coefficients, got {n}")
        pose = pose @ model.hands_components[:n]
    elif pose.shape[1] != 45:
        raise SequenceValidationError.single("mano.hand_pose", f"axis-angle needs 45 values, got {pose.shape[1]}")
    return pose if params.flat_hand_mean else pose + model.hands_mean


def local_rotations(params: ManoParams, model: ManoModel) -> FloatArray:
    """(T, 16, 3, 3) per-joint rotations relative to the parent (joint 0: global orient), MANO joint order."""
    aa = np.concatenate([np.asarray(params.global_orient, np.float64), full_hand_pose(params, model)], axis=1)
    t = aa.shape[0]
    return Rotation.from_rotvec(aa.reshape(-1, 3)).as_matrix().reshape(t, 16, 3, 3)


@dataclass(frozen=True)
class ManoDecoded:
    """``keypoints`` (T,21,3) MANO21 order, source frame; ``rotations`` (T,16,3,3) local per-joint rotations
    (MANO joint order, joint 0 = global orient); ``joints`` (T,16,3); ``vertices`` (T,V,3) when asked for."""

    keypoints: FloatArray
    rotations: FloatArray
    joints: FloatArray
    vertices: FloatArray | None = None


def decode_mano(
    params: ManoParams, side: Side, mano_dir: Path | str | None = None, return_vertices: bool = False
) -> ManoDecoded:
    """Decode MANO parameters with smplx into keypoints (21 = 16 joints + 5 tip vertices) and rotations."""
    import torch

    model = load_mano_model(side, mano_dir)
    hand_pose = full_hand_pose(params, model)
    t = hand_pose.shape[0]
    for name, arr in (("global_orient", params.global_orient), ("trans", params.trans)):
        if np.shape(arr) != (t, 3):
            raise SequenceValidationError.single(f"mano.{name}", f"must have shape ({t}, 3), got {np.shape(arr)}")
    betas = np.asarray(params.betas, dtype=np.float64).reshape(-1)
    n_betas = np.asarray(model.data["shapedirs"]).shape[-1]
    if betas.size > n_betas:
        raise SequenceValidationError.single(
            "mano.betas", f"the model has {n_betas} shape coefficients, got {betas.size}"
        )
    betas = np.pad(betas, (0, n_betas - betas.size))
    layer = _smplx_layer(model)
    with torch.no_grad():
        out = layer(
            betas=torch.from_numpy(np.tile(betas, (t, 1))),
            global_orient=torch.from_numpy(np.asarray(params.global_orient, np.float64)),
            hand_pose=torch.from_numpy(hand_pose),
            transl=torch.from_numpy(np.asarray(params.trans, np.float64)),
        )
    vertices = out.vertices.numpy()
    joints = out.joints.numpy()[:, :16]
    tips = vertices[:, list(model.tip_vertex_ids)]
    keypoints = np.concatenate([joints, tips], axis=1)[:, list(MANO21_ORDER)]
    return ManoDecoded(
        keypoints=keypoints,
        rotations=local_rotations(params, model),
        joints=joints,
        vertices=vertices if return_vertices else None,
    )
