"""Hypothesis strategies shared by the parser fuzz tests (``tests/unit/test_parser_fuzz.py``) and the API fuzz
test (``tests/integration/test_api_fuzz.py``): valid sequences in every variant, and mutations of them."""

from __future__ import annotations

import io
from typing import Any, Literal, cast

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from common.sequence import HandTrack, ManoParams, ObjectSpec, Sequence
from tests.support.queue_fixtures import tiny_sequence

DTYPES = st.sampled_from(["?", "i1", "<i8", ">i4", "<u8", "<f4", "<f8", ">f8", "<U1", "<U7", "<f2"])


def mesh_sequence() -> Sequence:
    seq = tiny_sequence(1, frames=4, name="mesh")
    corners = np.array([[x, y, z] for x in (0, 0.04) for y in (0, 0.04) for z in (0, 0.04)])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6]])
    seq.object = ObjectSpec(name="cube", mass_kg=0.2, mesh_vertices=corners, mesh_faces=faces, friction=0.8)
    return seq.validate()


def mano_sequence() -> Sequence:
    seq = tiny_sequence(2, frames=3, name="mano")
    t = seq.num_frames
    seq.hands.append(HandTrack(side="left", valid=np.ones(t, bool), mano=ManoParams(
        global_orient=np.zeros((t, 3)), hand_pose=np.zeros((t, 10)), trans=np.zeros((t, 3)), betas=np.zeros(10),
        pose_format="pca")))  # fmt: skip
    seq.meta = {"source": "fuzz"}
    return seq.validate()


def native_arrays(seq: Sequence) -> dict[str, np.ndarray]:
    from common.sequence_io import sequence_to_npz_bytes

    with np.load(io.BytesIO(sequence_to_npz_bytes(seq))) as data:
        return {k: data[k] for k in data.files}


VALID = [native_arrays(s) for s in (tiny_sequence(0).validate(), mesh_sequence(), mano_sequence())]
DEXYCB = {
    "fps": np.array(30.0), "subject": np.array("s01"), "sequence": np.array("seq"), "side": np.array("right"),
    "object_name": np.array("cube"), "hand_joints": np.full((4, 21, 3), 0.05, np.float32),
    "hand_valid": np.ones(4, bool), "mano_pose_pca": np.zeros((4, 48), np.float32),
    "mano_trans": np.zeros((4, 3), np.float32), "mano_betas": np.zeros(10, np.float32),
    "object_pose": np.tile(np.array([0, 0, 0.5, 1, 0, 0, 0], np.float32), (4, 1)), "world_from_camera": np.eye(4),
}  # fmt: skip



@st.composite
def random_arrays(draw: st.DrawFn) -> np.ndarray:
    dtype = np.dtype(draw(DTYPES))
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=25))
    if dtype.kind == "f":
        width = cast(Literal[16, 32, 64], dtype.itemsize * 8)
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


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=False) | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
    max_leaves=12,
)


def json_paths(doc: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += json_paths(v, (*prefix, k))
    elif isinstance(doc, list) and doc:
        out += json_paths(doc[0], (*prefix, 0))
    return out


ACTIONS = st.sampled_from(["flip", "cut", "insert", "zero"])
EDITS = st.tuples(st.floats(0, 1), ACTIONS, st.binary(min_size=1, max_size=8))


def mutate_json(data: st.DataObject, doc: Any, times: int, drop: bool = False) -> Any:
    """``doc`` with ``times`` values replaced by arbitrary JSON (``drop``: or keys removed); a mutation of the
    root replaces the whole document."""
    for _ in range(times):
        path = data.draw(st.sampled_from(json_paths(doc)))
        if not path:
            return data.draw(JSON_VALUES)
        parent = doc
        for part in path[:-1]:
            parent = parent[part]
        if drop and data.draw(st.booleans()) and isinstance(parent, dict):
            parent.pop(path[-1], None)
        else:
            parent[path[-1]] = data.draw(JSON_VALUES)
    return doc
