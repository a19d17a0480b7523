"""``common.npz_safe``: what is refused before anything is decompressed, and a round trip of what is read."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from common.errors import SequenceValidationError
from common.npz_safe import NpzLimits, SafeNpz, Spec
from common.npz_writer import deterministic_npz_bytes, npy_bytes


def test_round_trip_of_every_allowed_dtype_and_order() -> None:
    arrays = {
        "f": np.asfortranarray(np.arange(12.0).reshape(3, 4)), "i": np.arange(5, dtype=">i4"),
        "b": np.array([True, False]), "s": np.array("héllo"), "e": np.zeros((0, 3)),
    }  # fmt: skip
    with SafeNpz(deterministic_npz_bytes(arrays)) as npz:
        assert npz.files == list(arrays)
        for key, value in arrays.items():
            got = npz.get(key, Spec("biufU"))
            assert got.dtype == value.dtype and got.shape == value.shape
            np.testing.assert_array_equal(got, value)


def test_headers_are_checked_against_the_spec_before_decompressing() -> None:
    blob = deterministic_npz_bytes({"pose": np.zeros((100_000, 7))})
    npz = SafeNpz(blob, dim_limits={"T": 50})
    with pytest.raises(SequenceValidationError, match=r"pose: dimension 0 \(T\) is 100000, more than the limit of 50"):
        npz.get("pose", Spec("f", ("T", 7)))
    with pytest.raises(SequenceValidationError, match="pose: must have dtype kind int"):
        npz.get("pose", Spec("i", ("T", 7)))
    with pytest.raises(SequenceValidationError, match="pose: must have shape"):
        npz.get("pose", Spec("f", ("T",)))


def test_declared_sizes_and_members_are_limited() -> None:
    blob = deterministic_npz_bytes({"a": np.zeros(1000), "b": np.zeros(1000)})
    with pytest.raises(SequenceValidationError, match="a: declares 8128 bytes"):
        SafeNpz(blob, NpzLimits(max_member_bytes=4000))
    with pytest.raises(SequenceValidationError, match="add up to more than 10000"):
        SafeNpz(blob, NpzLimits(max_total_bytes=10_000))
    with pytest.raises(SequenceValidationError, match="has 2 members, more than 1"):
        SafeNpz(blob, NpzLimits(max_members=1))


def test_a_huge_zip_directory_is_refused_before_zipfile_parses_it() -> None:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for i in range(5000):
            zf.writestr(f"m{i}.npy", b"")
    with pytest.raises(SequenceValidationError, match="zip directory is"):
        SafeNpz(buf.getvalue())


def test_pickles_and_foreign_dtypes_are_refused() -> None:
    out = io.BytesIO()
    np.lib.format.write_array(out, np.array([None, {}], dtype=object), allow_pickle=True)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("o.npy", out.getvalue())
    with pytest.raises(SequenceValidationError, match="o: has dtype 'object'"):
        SafeNpz(buf.getvalue())
    for value in (np.zeros(2, complex), np.array([b"x"]), np.zeros(2, "datetime64[s]")):
        with pytest.raises(SequenceValidationError, match="x: has dtype"):
            SafeNpz(_zip({"x.npy": npy_bytes(value)}))


def _zip(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def test_a_member_cut_short_or_corrupted_is_refused() -> None:
    data = npy_bytes(np.arange(10_000.0))  # longer than the header read: the CRC is checked on the full read
    with pytest.raises(SequenceValidationError, match="x: its header declares shape"):
        SafeNpz(_zip({"x.npy": data[:-8]}))
    blob = bytearray(_zip({"x.npy": data}))
    blob[blob.find(data[-16:])] ^= 0xFF  # a data byte of the stored member: the CRC no longer matches
    with pytest.raises(SequenceValidationError, match="x: could not be decompressed"):
        SafeNpz(bytes(blob)).get("x", Spec("f"))
