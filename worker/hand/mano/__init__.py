"""MANO support (issue #6): read MANO model files without chumpy, decode parameters through smplx, and
describe a subject's MANO hand as the built-in articulated hand (geometry, hulls, hinge conversion, PCA).

torch/smplx are only imported when something is decoded (``pip install .[mano]``). Entry points:

* ``ensure_keypoints(seq)`` (here) — call after loading, before anything reads ``HandTrack.keypoints``;
  ``require_mano_models(seq)`` only checks that the model files of MANO-only hands exist (no torch);
* ``worker.hand.mano.decode``: ``decode_mano``, ``load_mano_model``;
* ``worker.hand.mano.hand_geometry``: ``mano_hand_geometry`` (HandGeometry + part hulls), ``rotations_to_hinges``,
  ``hinges_to_rotations``;
* ``worker.hand.mano.pose``: ``mano_reference`` (MANO counterpart of ``retarget_hand``), ``mano_pca_basis``,
  ``refined_mano_params`` / ``mano_result_arrays`` (refined hand -> MANO parameters);
* ``load_mano_pickle``, ``mano_model_path``, ``mano_available``, ``build_test_mano_model`` (here).
"""

from __future__ import annotations

from worker.hand.mano.ensure import ensure_keypoints, require_mano_models
from worker.hand.mano.pickle_io import load_mano_pickle, mano_available, mano_model_path
from worker.hand.mano.synthetic_model import build_test_mano_model

__all__ = [
    "build_test_mano_model",
    "ensure_keypoints",
    "load_mano_pickle",
    "mano_available",
    "mano_model_path",
    "require_mano_models",
]
