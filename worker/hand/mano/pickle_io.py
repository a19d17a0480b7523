"""MANO model files: locate them, and read the original pickles without chumpy installed.

The released ``MANO_RIGHT.pkl`` / ``MANO_LEFT.pkl`` are Python 2 pickles (``encoding='latin1'``) that hold a
few ``chumpy.ch.Ch`` objects (shapedirs, sometimes v_template/J) and a scipy sparse ``J_regressor``. chumpy
is unmaintained and does not install on current Python/NumPy, so the unpickler maps every ``chumpy.*``
class to a stand-in that keeps the pickled state; a Ch's state dict holds its value under ``x``, which is
all we need. Old scipy module paths (``scipy.sparse.csc``) are mapped to ``scipy.sparse``.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import ConfigurationError, ManoModelMissingError
from common.sequence import Side

#: Keys every MANO-format file must hold (the names of the released files).
REQUIRED_KEYS = (
    "v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f",
    "hands_components", "hands_mean",
)  # fmt: skip


class _ChumpyStandIn:
    """Receives a pickled chumpy object's state; ``value()`` gives the array it held."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.state: Any = None

    def __setstate__(self, state: Any) -> None:
        self.state = state

    def value(self) -> np.ndarray:
        state = self.state
        if isinstance(state, dict) and "x" in state:
            return np.asarray(state["x"], dtype=np.float64)
        raise ConfigurationError(
            "a chumpy object in the MANO file is an expression, not a stored array; "
            "re-save the file with plain NumPy arrays"
        )


class _NoChumpyUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if module == "chumpy" or module.startswith("chumpy."):
            return _ChumpyStandIn
        if module.startswith("scipy.sparse.") and module.rsplit(".", 1)[-1] in ("csc", "csr", "coo", "_csc", "_csr"):
            module = "scipy.sparse"
        return super().find_class(module, name)


def load_mano_pickle(path: Path | str) -> dict[str, Any]:
    """Read a MANO-format pickle into plain NumPy (chumpy values -> arrays; sparse J_regressor stays sparse)."""
    path = Path(path)
    with path.open("rb") as fh:
        raw = _NoChumpyUnpickler(fh, encoding="latin1").load()
    if not isinstance(raw, dict):
        raise ConfigurationError(f"{path} is not a MANO model file (expected a pickled dict)")
    out: dict[str, Any] = {}
    for key, val in raw.items():
        if not isinstance(val, _ChumpyStandIn):
            out[key] = val
        elif key in REQUIRED_KEYS or (isinstance(val.state, dict) and "x" in val.state):
            out[key] = val.value()
        # else: a chumpy expression in a key we never use (e.g. a derived ``J``): dropped
    missing = [k for k in REQUIRED_KEYS if k not in out]
    if missing:
        raise ConfigurationError(f"{path} is not a MANO model file: missing {', '.join(missing)}")
    return out


def mano_model_path(side: Side, mano_dir: Path | str | None = None) -> Path:
    """``<mano_dir>/MANO_<SIDE>.pkl``, or a clear error. Entry points pass ``HOI_REFINE_MANO_DIR`` as
    ``mano_dir``, so the errors name that setting."""
    directory = mano_dir
    fname = f"MANO_{side.upper()}.pkl"
    if directory is None:
        raise ManoModelMissingError(
            f"the {side} hand is given as MANO parameters without keypoints; decoding them needs {fname}, "
            "but HOI_REFINE_MANO_DIR is not set (point it at the folder holding MANO_RIGHT.pkl / MANO_LEFT.pkl "
            "from https://mano.is.tue.mpg.de, or give keypoints)"
        )
    path = Path(directory) / fname
    if not path.is_file():
        raise ManoModelMissingError(
            f"the {side} hand is given as MANO parameters without keypoints; decoding them needs {fname}, "
            f"but HOI_REFINE_MANO_DIR ({directory}) has no {fname}"
        )
    return path


def mano_available(sides: list[Side], mano_dir: Path | str | None = None) -> bool:
    try:
        for side in sides:
            mano_model_path(side, mano_dir)
    except ManoModelMissingError:
        return False
    return True
