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
from hypothesis.extra import numpy as hnp

from common.dexycb_native import load_dexycb_native
from common.errors import SequenceValidationError
from common.npz_writer import deterministic_npz_bytes
from common.sequence import HandTrack, ManoParams, ObjectSpec, Sequence
from common.sequence_io import sequence_from_json_bytes, sequence_from_npz_bytes, sequence_to_json_dict
from common.settings import get_settings
from tests.queue_fixtures import tiny_sequence
from tests.unit.test_dexycb_native import _write_tree

FUZZ = settings(max_examples=80, deadline=None, suppress_health_check=list(HealthCheck))


def _mesh_sequence() -> Sequence:
    seq = tiny_sequence(1, frames=4, name="mesh")
    corners = np.array([[x, y, z] for x in (0, 0.04) for y in (0, 0.04) for z in (0, 0.04)])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6]])
    seq.object = ObjectSpec(name="cube", mass_kg=0.2, mesh_vertices=corners, mesh_faces=faces, friction=0.8)
    return seq.validate()


def _mano_sequence() -> Sequence:
    seq = tiny_sequence(2, frames=3, name="mano")
    t = seq.num_frames
    seq.hands.append(HandTrack(side="left", valid=np.ones(t, bool), mano=ManoParams(
        global_orient=np.zeros((t, 3)), hand_pose=np.zeros((t, 10)), trans=np.zeros((t, 3)), betas=np.zeros(10),
        pose_format="pca")))  # fmt: skip
    seq.meta = {"source": "fuzz"}
    return seq.validate()


def _native_arrays(seq: Sequence) -> dict[str, np.ndarray]:
    from common.sequence_io import sequence_to_npz_bytes

    with np.load(io.BytesIO(sequence_to_npz_bytes(seq))) as data:
        return {k: data[k] for k in data.files}


VALID = [_native_arrays(s) for s in (tiny_sequence(0).validate(), _mesh_sequence(), _mano_sequence())]
DEXYCB = {
    "fps": np.array(30.0), "subject": np.array("s01"), "sequence": np.array("seq"), "side": np.array("right"),
    "object_name": np.array("cube"), "hand_joints": np.full((4, 21, 3), 0.05, np.float32),
    "hand_valid": np.ones(4, bool), "mano_pose_pca": np.zeros((4, 48), np.float32),
    "mano_trans": np.zeros((4, 3), np.float32), "mano_betas": np.zeros(10, np.float32),
    "object_pose": np.tile(np.array([0, 0, 0.5, 1, 0, 0, 0], np.float32), (4, 1)), "world_from_camera": np.eye(4),
}  # fmt: skip

DTYPES = st.sampled_from(["?", "i1", "<i8", ">i4", "<u8", "<f4", "<f8", ">f8", "<U1", "<U7", "<f2"])


@st.composite
def random_arrays(draw: st.DrawFn) -> np.ndarray:
    dtype = np.dtype(draw(DTYPES))
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=25))
    if dtype.kind == "f":
        width = dtype.itemsize * 8
        huge = float(np.finfo(dtype).max)  # beyond every plausible coordinate, representable in the dtype
        elements = st.floats(width=width) | st.sampled_from([huge, -huge, 0.0])
        return draw(hnp.arrays(dtype, shape, elements=elements))
    return draw(hnp.arrays(dtype, shape))


@st.composite
def mutated_members(draw: st.DrawFn, base: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    arrays = dict(base)
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from(sorted(arrays))) if arrays else "name"
        action = draw(st.sampled_from(["replace", "replace", "delete", "add", "reshape"]))
        if action == "delete":
            arrays.pop(key, None)
        elif action == "add":
            arrays[draw(st.sampled_from(["right_keypoints", "left_valid", "up", "world_from_camera", "x"]))] = draw(
                random_arrays()
            )
        elif action == "reshape" and key in arrays and arrays[key].size:
            arrays[key] = arrays[key].reshape(-1)
        else:
            arrays[key] = draw(random_arrays())
    return arrays


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


ACTIONS = st.sampled_from(["flip", "cut", "insert", "zero"])
EDITS = st.tuples(st.floats(0, 1), ACTIONS, st.binary(min_size=1, max_size=8))


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


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=False) | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
    max_leaves=12,
)


def _paths(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(doc, list) and doc:
        out += _paths(doc[0], (*prefix, 0))
    return out


@FUZZ
@given(data=st.data(), which=st.integers(0, len(VALID) - 1))
def test_native_json_with_mutated_values(data: st.DataObject, which: int) -> None:
    seqs = [tiny_sequence(0).validate(), _mesh_sequence(), _mano_sequence()]
    doc = sequence_to_json_dict(seqs[which])
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(_paths(doc)))
        if not path:
            doc = data.draw(JSON_VALUES)
            break
        parent = doc
        for part in path[:-1]:
            parent = parent[part]
        if data.draw(st.booleans()) and isinstance(parent, dict):
            parent.pop(path[-1], None)
        else:
            parent[path[-1]] = data.draw(JSON_VALUES)
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
    seq_dir = _write_tree(root)["s1"]
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
    from worker.mano import build_test_mano_model

    return build_test_mano_model(tmp_path_factory.mktemp("mano"), "right", seed=1).read_bytes()


@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
@given(edits=st.lists(EDITS, min_size=1, max_size=3))
def test_mano_pickle_with_mutated_bytes(
    mano_pickle: bytes, tmp_path_factory: pytest.TempPathFactory, edits: list[tuple[float, str, bytes]]
) -> None:
    """MANO files are the operator's configuration: a broken one is a ``ConfigurationError`` naming the file."""
    from common.errors import ConfigurationError
    from worker.mano import load_mano_pickle

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
    from worker.mano import load_mano_pickle

    class Evil:
        def __reduce__(self) -> tuple[Any, ...]:
            return (os.system, ("touch " + str(tmp_path / "pwned"),))

    path = tmp_path / "MANO_RIGHT.pkl"
    path.write_bytes(pickle.dumps({"v_template": Evil()}))
    with pytest.raises(ConfigurationError, match="may not reference"):
        load_mano_pickle(path)
    assert not (tmp_path / "pwned").exists()
