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


#: The only globals a MANO pickle may name (issue #16): a pickle can otherwise call any function on load.
#: NumPy arrays and dtypes, scipy's sparse matrices, and what Python 2 pickles reconstruct objects with.
ALLOWED_GLOBALS = {
    ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"), ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("scipy.sparse", "csc_matrix"), ("scipy.sparse", "csr_matrix"), ("scipy.sparse", "coo_matrix"),
    ("copyreg", "_reconstructor"), ("copy_reg", "_reconstructor"), ("_codecs", "encode"),
    ("builtins", "object"), ("__builtin__", "object"),
}  # fmt: skip

#: Per key: (dimensions, of which None = any size); checked after loading (all float64 but the integer ones).
EXPECTED_DIMS: dict[str, int] = {
    "v_template": 2, "shapedirs": 3, "posedirs": 3, "J_regressor": 2, "weights": 2, "kintree_table": 2,
    "f": 2, "hands_components": 2, "hands_mean": 1,
}  # fmt: skip
MAX_ARRAY_ELEMENTS = 50_000_000


class _NoChumpyUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if module == "chumpy" or module.startswith("chumpy."):
            return _ChumpyStandIn
        if module.startswith("scipy.sparse.") and module.rsplit(".", 1)[-1] in ("csc", "csr", "coo", "_csc", "_csr"):
            module = "scipy.sparse"
        if (module, name) not in ALLOWED_GLOBALS:
            raise pickle.UnpicklingError(f"a MANO file may not reference {module}.{name}")
        return super().find_class(module, name)


def _check_member(path: Path, key: str, value: Any) -> None:
    """Shapes and finiteness of the keys the hand model reads (the sparse J_regressor is checked densely)."""
    arr = value.toarray() if hasattr(value, "toarray") else value
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "biuf":
        raise ConfigurationError(f"{path.name}: {key} must be a numeric array, got {type(value).__name__}")
    if arr.ndim != EXPECTED_DIMS[key] or arr.size > MAX_ARRAY_ELEMENTS:
        raise ConfigurationError(f"{path.name}: {key} must have {EXPECTED_DIMS[key]} dimensions, got {arr.shape}")
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise ConfigurationError(f"{path.name}: {key} contains NaN or Inf")


def load_mano_pickle(path: Path | str) -> dict[str, Any]:
    """Read a MANO-format pickle into plain NumPy (chumpy values -> arrays; sparse J_regressor stays sparse)."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            raw = _NoChumpyUnpickler(fh, encoding="latin1").load()
    except ConfigurationError:
        raise
    except Exception as exc:  # truncated or hostile pickles raise many kinds of errors
        raise ConfigurationError(f"{path.name} is not a readable MANO model file: {exc}") from exc
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
    for key in REQUIRED_KEYS:
        _check_member(path, key, out[key])
    v_count = out["v_template"].shape[0]
    if out["v_template"].shape[1] != 3 or out["weights"].shape[0] != v_count or out["f"].max() >= v_count:
        raise ConfigurationError(f"{path.name}: v_template, weights and f disagree on the number of vertices")
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
