"""``common.npz_writer`` and the result file built on it: same arrays -> same bytes, still an NPZ, no clock in it."""

from __future__ import annotations

import io
import zipfile
from typing import Any

import numpy as np
import pytest

from common.npz_writer import FIXED_DATE_TIME, deterministic_npz_bytes
from common.result_format import CONTACT_KEYS, content_digest, read_arrays, read_summary, write_result_npz


def _arrays() -> dict[str, Any]:
    rng = np.random.default_rng(3)
    return {
        "pose": rng.normal(size=(5, 7)),
        "frames": np.arange(4, dtype=np.int64),
        "name": np.array("push"),
        "sides": np.array(["right", "left"]),
        "valid": np.array([True, False, True]),
        "blob": np.frombuffer(b"\x00\x01\x02", dtype=np.uint8),
        "empty": np.zeros((0, 3)),
    }


def test_same_arrays_give_same_bytes_and_np_load_reads_them_back() -> None:
    first = deterministic_npz_bytes(_arrays())
    assert deterministic_npz_bytes(_arrays()) == first
    with np.load(io.BytesIO(first), allow_pickle=False) as data:
        assert data.files == list(_arrays())  # the mapping's order
        for key, want in _arrays().items():
            got = data[key]
            assert got.dtype == want.dtype and got.shape == want.shape
            np.testing.assert_array_equal(got, want)


def test_members_carry_no_clock_and_are_deflated() -> None:
    with zipfile.ZipFile(io.BytesIO(deterministic_npz_bytes(_arrays()))) as zf:
        infos = zf.infolist()
        assert zf.testzip() is None
    assert [i.filename for i in infos] == [f"{k}.npy" for k in _arrays()]
    assert {i.date_time for i in infos} == {FIXED_DATE_TIME} == {(1980, 1, 1, 0, 0, 0)}
    assert {i.compress_type for i in infos} == {zipfile.ZIP_DEFLATED}


def test_object_arrays_are_refused() -> None:
    with pytest.raises(ValueError):
        deterministic_npz_bytes({"bad": np.array([{"a": 1}], dtype=object)})


def _result(wall_s: float) -> tuple[dict[str, Any], dict[str, Any]]:
    arrays: dict[str, Any] = {k: np.zeros((2, 3)) for k in CONTACT_KEYS}
    arrays["object_pose_sim"] = np.ones((4, 7))
    summary = {"kind": "refine", "timings": {"wall_s": wall_s, "sim_share": 0.5, "threads": 2, "steps": 40,
                                             "evaluations": 12}}
    return arrays, summary


def test_result_splits_wall_clock_from_counters() -> None:
    arrays, summary = _result(1.0)
    blob = write_result_npz(arrays, summary)
    assert read_summary(blob) == summary  # the timings merged back
    assert set(read_arrays(blob)) == set(arrays)  # JSON members are not arrays
    with zipfile.ZipFile(io.BytesIO(blob)) as zf:
        names = zf.namelist()
    assert names[:2] == ["summary_json.npy", "timings_json.npy"]
    assert names[2:] == sorted(names[2:])

    plain = write_result_npz(arrays, summary, wall_clock=False)
    assert read_summary(plain)["timings"] == {"steps": 40, "evaluations": 12}
    assert write_result_npz(*_result(9.0), wall_clock=False) == plain  # the clock no longer reaches the bytes

    other = write_result_npz(*_result(9.0))
    assert other != blob and content_digest(other) == content_digest(blob) == content_digest(plain)
    changed = dict(arrays, object_pose_sim=np.full((4, 7), 2.0))
    assert content_digest(write_result_npz(changed, summary)) != content_digest(blob)


def test_summary_without_timings_round_trips_unchanged() -> None:
    arrays, _ = _result(1.0)
    blob = write_result_npz(arrays, {"kind": "replay"})
    assert read_summary(blob) == {"kind": "replay"}
    with pytest.raises(ValueError, match="reserved"):
        write_result_npz({**arrays, "timings_json": np.array("{}")}, {"kind": "replay"})
