"""Deterministic NPZ bytes: the same arrays always give the same file (issue #3, "two runs, identical bytes").

``np.savez_compressed`` stamps every zip member with the current time (and the creating platform), so two
writes of equal arrays differ. ``deterministic_npz_bytes`` writes the same container — a zip of ``NAME.npy``
members that ``np.load`` reads as usual — with everything that could vary pinned:

* members in the order the mapping gives them (callers build their dicts in a fixed order; the result file
  puts its JSON members first and the arrays in sorted key order, see ``common.result_format``);
* every member dated 1980-01-01 00:00:00 (the earliest zip date), Unix file mode 0644, created on "Unix";
* ZIP_DEFLATED at zlib level 6, payloads written by ``np.lib.format.write_array`` (``allow_pickle=False``:
  object arrays are refused, as ``np.load(allow_pickle=False)`` would refuse to read them back).

Bytes are equal for equal inputs on one build; a different zlib could compress differently, which is why
``common.result_format.content_digest`` hashes the uncompressed members.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Mapping
from typing import Any

import numpy as np

#: The zip epoch: DOS dates cannot go earlier, and any fixed value makes the bytes independent of the clock.
FIXED_DATE_TIME = (1980, 1, 1, 0, 0, 0)
_COMPRESS_LEVEL = 6  # zlib's default, named so a changed Python default cannot change the bytes
_UNIX = 3  # ZipInfo.create_system: otherwise 0 on Windows, 3 elsewhere
_FILE_MODE = 0o100644  # regular file, rw-r--r--, in the high 16 bits of external_attr


def npy_bytes(array: Any) -> bytes:
    """One ``.npy`` payload (header + data) as ``np.save`` would write it, pickles refused."""
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.asanyarray(array), allow_pickle=False)
    return buf.getvalue()


def deterministic_npz_bytes(arrays: Mapping[str, Any]) -> bytes:
    """A compressed NPZ of ``arrays`` (members ``KEY.npy`` in the mapping's order); see the module docstring."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, mode="w", compression=zipfile.ZIP_DEFLATED, compresslevel=_COMPRESS_LEVEL) as zf:
        for key, value in arrays.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=FIXED_DATE_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.create_system = _UNIX
            info.external_attr = _FILE_MODE << 16
            zf.writestr(info, npy_bytes(value), compress_type=zipfile.ZIP_DEFLATED, compresslevel=_COMPRESS_LEVEL)
    return buf.getvalue()
