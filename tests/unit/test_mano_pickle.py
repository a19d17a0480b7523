"""MANO model files: read without chumpy; clear errors when the model is not configured (no torch needed)."""

from __future__ import annotations

import importlib.util
import pickle
from pathlib import Path

import numpy as np
import pytest

from common.errors import ConfigurationError, ManoModelMissingError
from common.sequence import HandTrack, ManoParams, ObjectSpec, Sequence
from worker.hand.mano import build_test_mano_model, ensure_keypoints, load_mano_pickle, mano_model_path
from worker.hand.mano.synthetic_model import MANO_PARENTS, skeleton


def test_reads_chumpy_pickle_without_chumpy(tmp_path: Path) -> None:
    path = build_test_mano_model(tmp_path, "right", seed=3)
    assert path.name == "MANO_RIGHT.pkl"
    assert b"chumpy.ch" in path.read_bytes()  # the file really references chumpy ...
    if importlib.util.find_spec("chumpy") is None:  # ... which is not installed: a plain unpickle fails
        with path.open("rb") as fh, pytest.raises(ModuleNotFoundError, match="chumpy"):
            pickle.load(fh, encoding="latin1")
    data = load_mano_pickle(path)
    v = data["v_template"]
    assert isinstance(v, np.ndarray) and v.dtype == np.float64 and v.shape[1] == 3
    assert data["shapedirs"].shape == (len(v), 3, 10) and data["posedirs"].shape == (len(v), 3, 135)
    assert data["weights"].shape == (len(v), 16)
    np.testing.assert_allclose(data["weights"].sum(axis=1), 1.0)
    assert type(data["J_regressor"]).__module__.startswith("scipy.sparse")
    joints = data["J_regressor"] @ v
    np.testing.assert_allclose(joints, skeleton()[0], atol=1e-12)  # each joint is its ring's centre
    np.testing.assert_allclose(data["J"], joints)
    assert data["kintree_table"].shape == (2, 16) and tuple(data["kintree_table"][0, 1:]) == MANO_PARENTS[1:]
    comps = data["hands_components"]
    np.testing.assert_allclose(comps @ comps.T, np.eye(45), atol=1e-10)
    assert data["f"].max() < len(v) and data["hands_mean"].shape == (45,)
    left = load_mano_pickle(build_test_mano_model(tmp_path, "left", seed=3))
    np.testing.assert_allclose(left["v_template"], v * [1, -1, 1])


def test_not_a_mano_file(tmp_path: Path) -> None:
    bad = tmp_path / "MANO_RIGHT.pkl"
    bad.write_bytes(pickle.dumps({"v_template": np.zeros((3, 3))}))
    with pytest.raises(ConfigurationError, match="missing shapedirs"):
        load_mano_pickle(bad)


def _mano_only_sequence() -> Sequence:
    t = 3
    mano = ManoParams(
        global_orient=np.zeros((t, 3)), hand_pose=np.zeros((t, 10)), trans=np.zeros((t, 3)), betas=np.zeros(10),
        pose_format="pca",
    )  # fmt: skip
    return Sequence(
        name="mano-only", fps=30.0,
        object=ObjectSpec(name="box", mass_kg=0.1, primitive="box", size=np.array([0.02, 0.02, 0.02])),
        object_pose=np.tile([0.0, 0, 0.02, 1, 0, 0, 0], (t, 1)),
        hands=[HandTrack(side="left", valid=np.ones(t, bool), mano=mano)],
    ).validate()  # fmt: skip


def test_missing_model_names_the_setting(tmp_path: Path) -> None:
    seq = _mano_only_sequence()
    with pytest.raises(ManoModelMissingError, match=r"MANO_LEFT\.pkl.*HOI_REFINE_MANO_DIR is not set"):
        ensure_keypoints(seq)
    build_test_mano_model(tmp_path, "right")
    with pytest.raises(ManoModelMissingError, match=rf"HOI_REFINE_MANO_DIR \({tmp_path}\) has no MANO_LEFT\.pkl"):
        ensure_keypoints(seq, tmp_path)
    assert mano_model_path("right", tmp_path) == tmp_path / "MANO_RIGHT.pkl"
    assert ManoModelMissingError.http_status == 422


def test_hands_with_keypoints_need_no_model() -> None:
    seq = _mano_only_sequence()
    seq.hands[0].keypoints = np.zeros((3, 21, 3))
    assert ensure_keypoints(seq) is seq


def test_chumpy_expressions(tmp_path: Path) -> None:
    """A chumpy expression (state without ``x``) is dropped from optional keys and rejected in required ones."""
    import sys
    import types

    class add:  # chumpy.ch_ops.add
        def __init__(self, a: object, b: object) -> None:
            self.a, self.b = a, b

    add.__module__, add.__qualname__ = "chumpy.ch_ops", "add"
    ops, package = types.ModuleType("chumpy.ch_ops"), types.ModuleType("chumpy")
    ops.add = add  # type: ignore[attr-defined]

    def dump(data: dict[str, object], path: Path) -> Path:
        sys.modules.update({"chumpy": package, "chumpy.ch_ops": ops})
        try:
            path.write_bytes(pickle.dumps(data, protocol=2))
        finally:
            del sys.modules["chumpy"], sys.modules["chumpy.ch_ops"]
        return path

    data = load_mano_pickle(build_test_mano_model(tmp_path, "right"))
    assert "J" not in load_mano_pickle(dump(dict(data, J=add(1, 2)), tmp_path / "a.pkl"))
    with pytest.raises(ConfigurationError, match="expression"):
        load_mano_pickle(dump(dict(data, shapedirs=add(1, 2)), tmp_path / "b.pkl"))
