"""``ensure_keypoints``: make every hand of a sequence carry keypoints, decoding MANO parameters if needed.

Call it after loading and before anything reads ``HandTrack.keypoints`` (inspect, replay, refine, the
worker). Hands that already have keypoints are left alone; MANO-only hands are decoded through smplx with
the model in ``HOI_REFINE_MANO_DIR`` (or ``mano_dir``), else ``ManoModelMissingError`` names that setting
and the missing file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from common.sequence import Sequence
from worker.hand.mano.pickle_io import mano_model_path


def require_mano_models(seq: Sequence, mano_dir: Path | str | None = None) -> list[int]:
    """Indices of the MANO-only hands (MANO parameters, no keypoints); raises ``ManoModelMissingError`` (naming
    ``HOI_REFINE_MANO_DIR`` and the file) when the model of one of them is missing. Cheap: imports no torch,
    so ``hoi-refine inspect`` can call it."""
    todo = [i for i, h in enumerate(seq.hands) if h.keypoints is None and h.mano is not None]
    for i in todo:
        mano_model_path(seq.hands[i].side, mano_dir)
    return todo


def ensure_keypoints(seq: Sequence, mano_dir: Path | str | None = None) -> Sequence:
    """``seq`` itself when no hand needs decoding, else a copy whose MANO-only hands have keypoints."""
    todo = require_mano_models(seq, mano_dir)  # fails on a missing file before importing torch
    if not todo:
        return seq
    from worker.hand.mano.decode import decode_mano

    hands = list(seq.hands)
    for i in todo:
        hand = hands[i]
        assert hand.mano is not None
        keypoints = decode_mano(hand.mano, hand.side, mano_dir).keypoints
        keypoints[~hand.valid] = 0.0
        hands[i] = dataclasses.replace(hand, keypoints=keypoints)
    meta = dict(seq.meta, keypoints_from="MANO (smplx)")
    return dataclasses.replace(seq, hands=hands, meta=meta)
