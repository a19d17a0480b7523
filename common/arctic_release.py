"""The ARCTIC release layout (``raw_seqs/<subject>/<seq>.mano.npy`` + ``.object.npy``): not read yet."""

from __future__ import annotations

from pathlib import Path

from common.errors import UnsupportedFormatError
from common.sequence import Sequence


def load_arctic_release(path: Path, object_dir: Path | None = None, max_frames: int | None = None) -> Sequence:
    raise UnsupportedFormatError(f"{path.name}: the ARCTIC release layout is not read yet (a dexmachina-processed "
                                 "<object>_use_NN.npy is)")
