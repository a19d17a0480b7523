"""Property-based fuzz of the sequence parsers (issue #16): whatever the bytes, a parser gives a valid
``Sequence`` or a ``SequenceValidationError`` whose every problem names a field, never another exception.

Inputs are mutated valid files: native NPZ (primitive, mesh and MANO variants) with members replaced,
removed or added (arrays of any dtype, shape and value, NaN/Inf and huge numbers included) and with raw
byte flips, cuts and insertions; native JSON documents with values replaced at any path; DexYCB
development NPZs; and DexYCB release folders with meta.yml values and pose.npz members replaced.
Example counts are moderate so the module runs in well under a minute.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.dexycb_native import load_dexycb_native
from common.errors import SequenceValidationError
from common.npz_writer import deterministic_npz_bytes
from common.sequence import Sequence
from common.sequence_io import sequence_from_json_bytes, sequence_from_npz_bytes, sequence_to_json_dict
from common.settings import get_settings
from tests.support.dexycb_tree import write_tree
from tests.support.fuzz_strategies import (
    DEXYCB,
    EDITS,
    VALID,
    mano_sequence,
    mesh_sequence,
    mutate_json,
    mutated_members,
)
from tests.support.queue_fixtures import tiny_sequence

FUZZ = settings(max_examples=80, deadline=None, suppress_health_check=list(HealthCheck))


def _check(parse: Any) -> None:
    try:
        seq = parse()
    except SequenceValidationError as exc:
        assert exc.problems and all(p.field and p.problem for p in exc.problems), exc.problems
        return
    assert isinstance(seq, Sequence) and seq.num_frames >= 2
    seq.validate()  # what came back is valid as it stands


@FUZZ
@given(data=st.data(), which=st.integers(0, len(VALID) - 1))
def test_native_npz_with_mutated_members(data: st.DataObject, which: int) -> None:
    arrays = data.draw(mutated_members(VALID[which]))
    _check(lambda: sequence_from_npz_bytes(deterministic_npz_bytes(arrays), max_frames=50))


@FUZZ
@given(
    which=st.integers(0, len(VALID) - 1),
    stored=st.booleans(),
    edits=st.lists(EDITS, min_size=1, max_size=4),
)
def test_native_npz_with_mutated_bytes(which: int, stored: bool, edits: list[tuple[float, str, bytes]]) -> None:
    blob = bytearray(_zip(VALID[which], stored))
    for where, action, data in edits:
        i = int(where * (len(blob) - 1))
        if action == "flip":
            blob[i] ^= data[0] or 1
        elif action == "cut":
            del blob[i:]
        elif action == "insert":
            blob[i:i] = data
        else:
            blob[i : i + len(data)] = bytes(len(data))
        if not blob:
            break
    _check(lambda: sequence_from_npz_bytes(bytes(blob), max_frames=50))


def _zip(arrays: dict[str, np.ndarray], stored: bool) -> bytes:
    if not stored:
        return deterministic_npz_bytes(arrays)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for key, value in arrays.items():
            out = io.BytesIO()
            np.lib.format.write_array(out, value)
            zf.writestr(f"{key}.npy", out.getvalue())
    return buf.getvalue()


@FUZZ
@given(data=st.data(), which=st.integers(0, len(VALID) - 1))
def test_native_json_with_mutated_values(data: st.DataObject, which: int) -> None:
    seqs = [tiny_sequence(0).validate(), mesh_sequence(), mano_sequence()]
    doc = sequence_to_json_dict(seqs[which])
    doc = mutate_json(data, doc, data.draw(st.integers(1, 3)), drop=True)
    text = json.dumps(doc).encode()
    if data.draw(st.booleans()):  # and sometimes broken text: cut, or deep nesting, or a NaN literal
        text = data.draw(st.sampled_from([text[: len(text) // 2], b"[" * 100_000, text.replace(b"0.0", b"NaN", 1)]))
    _check(lambda: sequence_from_json_bytes(text, max_frames=50))


@pytest.fixture()
def ycb_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    ycb = tmp_path / "ycb"
    ycb.mkdir()
    corners = [(x, y, z) for x in (-0.03, 0.03) for y in (-0.03, 0.03) for z in (-0.03, 0.03)]
    faces = [(1, 3, 2), (1, 2, 5), (1, 5, 3), (8, 6, 7), (8, 7, 4), (8, 4, 6),
             (2, 4, 3), (2, 6, 4), (5, 7, 6), (5, 6, 2), (3, 7, 5), (3, 4, 7)]  # fmt: skip
    lines = [f"v {x} {y} {z}" for x, y, z in corners] + [f"f {a} {b} {c}" for a, b, c in faces]
    (ycb / "cube.obj").write_text("\n".join(lines) + "\n")
    (ycb / "objects.json").write_text(json.dumps({"cube": {"mass_kg": 0.2}}))
    monkeypatch.setenv("HOI_REFINE_YCB_DIR", str(ycb))
    get_settings.cache_clear()
    return ycb


@FUZZ
@given(data=st.data())
def test_dexycb_npz_with_mutated_members(ycb_dir: Path, data: st.DataObject) -> None:
    base = dict(DEXYCB)
    _check(lambda: sequence_from_npz_bytes(deterministic_npz_bytes(base), max_frames=50))  # the unmutated file
    arrays = data.draw(mutated_members(base))
    arrays.pop("format", None)
    _check(lambda: sequence_from_npz_bytes(deterministic_npz_bytes(arrays), max_frames=50))


YAML_VALUES = st.none() | st.booleans() | st.integers(-5, 10**8) | st.text(max_size=6) | st.lists(
    st.integers(-2, 30) | st.text(max_size=4), max_size=3
)


@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_dexycb_folder_with_mutated_meta_and_poses(
    tmp_path_factory: pytest.TempPathFactory, data: st.DataObject
) -> None:
    root = tmp_path_factory.mktemp("dexycb")
    seq_dir = write_tree(root)["s1"]
    if data.draw(st.booleans()):
        meta = yaml.safe_load((seq_dir / "meta.yml").read_text())
        meta[data.draw(st.sampled_from(sorted(meta)))] = data.draw(YAML_VALUES)
        (seq_dir / "meta.yml").write_text(yaml.safe_dump(meta))
    else:
        with np.load(seq_dir / "pose.npz") as npz:
            arrays = data.draw(mutated_members({k: npz[k] for k in npz.files}))
        (seq_dir / "pose.npz").write_bytes(deterministic_npz_bytes(arrays))
    _check(lambda: load_dexycb_native(seq_dir, max_frames=50))


@pytest.fixture(scope="module")
def mano_pickle(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    from worker.hand.mano import build_test_mano_model

    return build_test_mano_model(tmp_path_factory.mktemp("mano"), "right", seed=1).read_bytes()


@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
@given(edits=st.lists(EDITS, min_size=1, max_size=3))
def test_mano_pickle_with_mutated_bytes(
    mano_pickle: bytes, tmp_path_factory: pytest.TempPathFactory, edits: list[tuple[float, str, bytes]]
) -> None:
    """MANO files are the operator's configuration: a broken one is a ``ConfigurationError`` naming the file."""
    from common.errors import ConfigurationError
    from worker.hand.mano import load_mano_pickle

    blob = bytearray(mano_pickle)
    for where, action, data in edits:
        i = int(where * (len(blob) - 1))
        if action == "flip":
            blob[i] ^= data[0] or 1
        elif action == "cut":
            del blob[max(i, 1) :]
        elif action == "insert":
            blob[i:i] = data
        else:
            blob[i : i + len(data)] = bytes(len(data))
    path = tmp_path_factory.mktemp("bad") / "MANO_RIGHT.pkl"
    path.write_bytes(bytes(blob))
    try:
        model = load_mano_pickle(path)
    except ConfigurationError as exc:
        assert "MANO" in str(exc) or path.name in str(exc)
        return
    assert isinstance(model["v_template"], np.ndarray) and model["v_template"].shape[1] == 3


def test_mano_pickle_may_not_call_functions(tmp_path: Path) -> None:
    import os
    import pickle

    from common.errors import ConfigurationError
    from worker.hand.mano import load_mano_pickle

    class Evil:
        def __reduce__(self) -> tuple[Any, ...]:
            return (os.system, ("touch " + str(tmp_path / "pwned"),))

    path = tmp_path / "MANO_RIGHT.pkl"
    path.write_bytes(pickle.dumps({"v_template": Evil()}))
    with pytest.raises(ConfigurationError, match="may not reference"):
        load_mano_pickle(path)
    assert not (tmp_path / "pwned").exists()
