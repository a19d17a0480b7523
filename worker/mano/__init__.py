"""MANO support (issue #6): read MANO model files without chumpy, decode parameters through smplx, and
describe a subject's MANO hand as the built-in articulated hand (geometry, hulls, hinge conversion, PCA).

torch/smplx are only imported when something is decoded (``pip install .[mano]``). Entry points:
``ensure_keypoints(seq)`` (call before reading keypoints), ``decode_mano``, ``mano_hand_geometry``,
``mano_reference``, ``hand_pose_to_mano``, ``mano_pca_basis``, ``load_mano_pickle``, ``build_test_mano_model``.
"""

from __future__ import annotations

from worker.mano.ensure import ensure_keypoints
from worker.mano.pickle_io import load_mano_pickle, mano_available, mano_model_path
from worker.mano.synthetic_model import build_test_mano_model

__all__ = [
    "build_test_mano_model",
    "ensure_keypoints",
    "load_mano_pickle",
    "mano_available",
    "mano_model_path",
]
