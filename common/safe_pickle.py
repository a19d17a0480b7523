"""Read ``.npy`` files that hold pickled Python objects (``np.save`` of a dict) without running their code.

``np.load(allow_pickle=True)`` lets a file call any function while it loads. The datasets that ship their
recordings this way (ARCTIC's ``raw_seqs``, the dexmachina-processed ARCTIC files) hold only dicts of NumPy
arrays, so the unpickler here resolves nothing but what rebuilds arrays, dtypes and scalars; any other global a
file names is refused with an ``UnsupportedFormatError``.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import UnsupportedFormatError

#: The globals a pickled dict of arrays needs (NumPy 1.x and 2.x module paths).
ARRAY_GLOBALS = frozenset({
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
    ("copyreg", "_reconstructor"), ("builtins", "object"),
})  # fmt: skip


class _ArrayUnpickler(pickle.Unpickler):
    def __init__(self, file: Any, allowed: frozenset[tuple[str, str]], source: str) -> None:
        super().__init__(file, encoding="latin1")
        self._allowed, self._source = allowed, source

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self._allowed:
            return super().find_class(module, name)
        raise UnsupportedFormatError(f"{self._source}: refuses to load {module}.{name} (only NumPy arrays are read)")


def load_object_npy(path: Path, allowed: frozenset[tuple[str, str]] = ARRAY_GLOBALS) -> Any:
    """The object an ``.npy`` file holds: a plain array as it is, a pickled object (a 0-d object array, as
    ``np.save`` writes a dict) unpickled with only ``allowed`` globals and unwrapped."""
    with open(path, "rb") as f:
        try:
            version = np.lib.format.read_magic(f)
            header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                      else np.lib.format.read_array_header_2_0)(f)  # fmt: skip
        except ValueError as exc:
            raise UnsupportedFormatError(f"{path.name}: not a NumPy .npy file ({exc})") from exc
        dtype = header[2]
        if not dtype.hasobject:
            f.seek(0)
            return np.load(f, allow_pickle=False)
        try:
            value = _ArrayUnpickler(f, allowed, path.name).load()
        except (pickle.UnpicklingError, EOFError, AttributeError, TypeError, ValueError) as exc:
            raise UnsupportedFormatError(f"{path.name}: unreadable pickled data ({type(exc).__name__})") from exc
    if isinstance(value, np.ndarray) and value.dtype.hasobject and value.shape == ():
        return value.item()
    return value
