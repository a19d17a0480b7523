"""Reading NPZ files from untrusted bytes without trusting them (issue #16).

``np.load`` decompresses a member in full before anyone can look at its shape, so a small upload whose
member inflates to gigabytes (a zip bomb) costs that much memory. ``SafeNpz`` instead:

1. reads the zip's central directory (bounded by the upload's size) and refuses encrypted members,
   compression methods other than stored/deflate, duplicate or non-``.npy`` names, too many members,
   and declared uncompressed sizes beyond the per-member and total byte limits;
2. streams only each member's ``.npy`` header (a few hundred bytes are inflated) and checks its dtype
   (booleans, integers, floats and unicode strings; never objects, structured or sub-array dtypes), its
   shape, and that header + ``prod(shape) * itemsize`` is exactly the declared size;
3. on ``get(key, spec)``, checks the header against what the caller expects (dtype kinds, number of
   dimensions, each dimension's limit: frames, mesh vertices, ...) *before* decompressing, then inflates
   exactly the declared number of bytes into a preallocated array. A member whose data inflates to more
   than it declared is cut there and fails zip's CRC check.

Every problem is a ``SequenceValidationError`` naming the member (or ``sequence`` for the container).
"""

from __future__ import annotations

import io
import math
import re
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.errors import SequenceValidationError
from common.safe_text import shown as _shown

#: Dtype kinds a member may have: bool, signed/unsigned integers, floats, unicode strings.
ALLOWED_KINDS = "biufU"
#: ``.npy`` headers are a short Python dict literal; NumPy itself caps them at 10000 bytes.
MAX_HEADER_BYTES = 4096
MAX_NDIM = 4
#: Central-directory bytes allowed per member (46 fixed + name + extra fields, generously).
MAX_DIRECTORY_ENTRY_BYTES = 1024
_READ_CHUNK = 1 << 20
_SAFE_KEY = re.compile(r"[A-Za-z0-9_]{1,100}")
#: Whole-file problems name this field (the multipart part holding the file has the same name).
CONTAINER_FIELD = "sequence"


@dataclass(frozen=True)
class NpzLimits:
    """Byte and count limits of one NPZ file (defaults suit every sequence this project reads)."""

    #: Largest uncompressed member (bytes).
    max_member_bytes: int = 64 * 1024 * 1024
    #: Largest sum of the uncompressed members (bytes).
    max_total_bytes: int = 128 * 1024 * 1024
    #: Members: an articulated object of ``common.articulation.MAX_PARTS`` parts held by two MANO hands has 91.
    max_members: int = 128


@dataclass(frozen=True)
class MemberHeader:
    key: str
    shape: tuple[int, ...]
    dtype: np.dtype[Any]
    fortran_order: bool
    header_bytes: int
    info: zipfile.ZipInfo

    @property
    def data_bytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


@dataclass(frozen=True)
class Spec:
    """What a member must look like. ``dims`` holds, per dimension, an exact size (int) or a name of
    ``SafeNpz.dim_limits`` (a bounded size, e.g. ``"T"`` frames); ``None`` for dims means any shape."""

    kinds: str
    dims: tuple[int | str, ...] | None = None
    #: For 0-d or 1-d string members: the most characters per string.
    max_chars: int = 1000


def _fail(field: str, problem: str) -> SequenceValidationError:
    return SequenceValidationError.single(field, problem)


class SafeNpz:
    """A read-only view of an NPZ with the same ``files`` / ``in`` / ``with`` use as ``np.load``'s result."""

    def __init__(self, blob: bytes, limits: NpzLimits | None = None, dim_limits: dict[str, int] | None = None):
        self.limits = limits or NpzLimits()
        #: Upper bounds of named dimensions (``"T"`` -> max frames, ...); checked before decompressing.
        self.dim_limits = dict(dim_limits or {})
        _check_directory_size(blob, self.limits.max_members * MAX_DIRECTORY_ENTRY_BYTES)
        try:
            self._zip = zipfile.ZipFile(io.BytesIO(blob))
            infos = self._zip.infolist()
        except Exception as exc:  # zipfile raises BadZipFile, ValueError, struct.error, ... on corrupt input
            raise _fail(CONTAINER_FIELD, f"is not a readable NPZ (zip) file ({type(exc).__name__})") from exc
        if len(infos) > self.limits.max_members:
            raise _fail(CONTAINER_FIELD, f"has {len(infos)} members, more than {self.limits.max_members}")
        self._headers: dict[str, MemberHeader] = {}
        total = 0
        for info in infos:
            header = self._read_header(info)
            if header.key in self._headers:
                raise _fail(CONTAINER_FIELD, f"holds the member {_shown(header.key)} twice")
            total += info.file_size
            if total > self.limits.max_total_bytes:
                raise _fail(CONTAINER_FIELD, f"members add up to more than {self.limits.max_total_bytes} bytes "
                            "uncompressed")  # fmt: skip
            self._headers[header.key] = header

    # ------------------------------------------------------------------ mapping-like API
    @property
    def files(self) -> list[str]:
        return list(self._headers)

    def __contains__(self, key: object) -> bool:
        return key in self._headers

    def __iter__(self) -> Iterator[str]:
        return iter(self._headers)

    def __enter__(self) -> SafeNpz:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._zip.close()

    def header(self, key: str) -> MemberHeader:
        return self._headers[key]

    # ------------------------------------------------------------------ reading
    def get(self, key: str, spec: Spec, field: str | None = None) -> np.ndarray:
        """The member ``key`` after checking its header against ``spec``; finite when floating."""
        field = field or key
        if key not in self._headers:
            raise _fail(field, "is missing from the NPZ file")
        h = self._headers[key]
        if h.dtype.kind not in spec.kinds:
            raise _fail(field, f"must have dtype kind {_kinds(spec.kinds)}, got {h.dtype.str}")
        if spec.dims is not None:
            if len(h.shape) != len(spec.dims):
                want = "(" + ", ".join(str(d) for d in spec.dims) + ")"
                raise _fail(field, f"must have shape {want}, got {h.shape}")
            for axis, (size, want_dim) in enumerate(zip(h.shape, spec.dims, strict=True)):
                if isinstance(want_dim, int):
                    if size != want_dim:
                        raise _fail(field, f"dimension {axis} must be {want_dim}, got {size} (shape {h.shape})")
                elif want_dim in self.dim_limits and size > self.dim_limits[want_dim]:
                    raise _fail(field, f"dimension {axis} ({want_dim}) is {size}, more than the limit of "
                                f"{self.dim_limits[want_dim]}")  # fmt: skip
        if h.dtype.kind == "U" and h.dtype.itemsize // 4 > spec.max_chars:
            raise _fail(field, f"strings may hold at most {spec.max_chars} characters (dtype {h.dtype.str})")
        arr = self._inflate(h, field)
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            bad = np.argwhere(~np.isfinite(arr))[0] if arr.ndim else ()
            raise _fail(field, f"contains NaN or Inf (first at index {tuple(int(b) for b in bad)})")
        return arr

    def _inflate(self, h: MemberHeader, field: str) -> np.ndarray:
        out = np.empty(h.shape, dtype=h.dtype, order="F" if h.fortran_order else "C")
        # Filled in place, in memory order: no second copy of the data is ever made.
        flat: Any = out.reshape(-1, order="A").view(np.uint8)
        view = memoryview(flat) if out.size else memoryview(b"")
        try:
            with self._zip.open(h.info) as fp:
                fp.read(h.header_bytes)
                pos = 0
                while pos < h.data_bytes:
                    chunk = fp.read(min(_READ_CHUNK, h.data_bytes - pos))
                    if not chunk:
                        raise _fail(field, "ends before the data its header declares")
                    view[pos : pos + len(chunk)] = chunk
                    pos += len(chunk)
                fp.read(1)  # reach the end: zipfile checks the CRC there
        except SequenceValidationError:
            raise
        except Exception as exc:  # bad CRC, corrupt deflate stream, ...
            raise _fail(field, f"could not be decompressed ({type(exc).__name__})") from exc
        return out

    def _read_header(self, info: zipfile.ZipInfo) -> MemberHeader:
        name = info.filename
        if not name.endswith(".npy") or len(name) > 200:
            raise _fail(CONTAINER_FIELD, f"member {_shown(name)} is not a .npy array")
        key = name[:-4]
        if not _SAFE_KEY.fullmatch(key):
            # Member names become field names in error answers: only plain identifiers are echoed.
            raise _fail(CONTAINER_FIELD, f"member {_shown(name)} has a name other than letters, digits and _")
        if info.flag_bits & 0x1:
            raise _fail(key, "is encrypted")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise _fail(key, "uses a compression method other than stored or deflate")
        if info.file_size > self.limits.max_member_bytes:
            raise _fail(key, f"declares {info.file_size} bytes uncompressed, more than the limit of "
                        f"{self.limits.max_member_bytes}")  # fmt: skip
        try:
            with self._zip.open(info) as fp:
                bounded = io.BytesIO(fp.read(min(info.file_size, MAX_HEADER_BYTES)))
            version = np.lib.format.read_magic(bounded)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(bounded, max_header_size=MAX_HEADER_BYTES)
            elif version in ((2, 0), (3, 0)):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(bounded, max_header_size=MAX_HEADER_BYTES)
            else:
                raise ValueError(f"unknown .npy version {version}")
        except Exception as exc:  # corrupt stream, bad magic, header not a dict literal, unknown dtype, ...
            raise _fail(key, f"is not a valid .npy array ({type(exc).__name__})") from exc
        dtype = np.dtype(dtype)
        if dtype.hasobject or dtype.names is not None or dtype.subdtype is not None or dtype.kind not in ALLOWED_KINDS:
            raise _fail(key, f"has dtype {_shown(str(dtype))}; only booleans, numbers and strings are read")
        if len(shape) > MAX_NDIM:
            raise _fail(key, f"has {len(shape)} dimensions, more than {MAX_NDIM}")
        header = MemberHeader(key, tuple(int(s) for s in shape), dtype, bool(fortran), bounded.tell(), info)
        if header.header_bytes + header.data_bytes != info.file_size:
            raise _fail(key, f"its header declares shape {header.shape} of {dtype.str} ({header.data_bytes} bytes) "
                        f"but the zip entry holds {info.file_size - header.header_bytes}")  # fmt: skip
        return header


def _check_directory_size(blob: bytes, limit: int) -> None:
    """Refuse a central directory larger than ``limit`` bytes *before* ``zipfile`` parses it: it builds one
    ``ZipInfo`` (hundreds of bytes) per ~50-byte entry, so a directory of a million tiny entries would cost
    ten times the upload in memory. The end-of-directory record is within the last 64 KiB + 22 bytes."""
    end = blob.rfind(b"PK\x05\x06", max(0, len(blob) - 65536 - 22))
    if end < 0 or end + 22 > len(blob):
        return  # not a zip: zipfile says so
    size_cd = int.from_bytes(blob[end + 12 : end + 16], "little")
    if size_cd > limit:
        raise _fail(CONTAINER_FIELD, f"its zip directory is {size_cd} bytes, more than {limit} (too many members)")


def _kinds(kinds: str) -> str:
    names = {"b": "bool", "i": "int", "u": "uint", "f": "float", "U": "str"}
    return "/".join(names[k] for k in kinds)

