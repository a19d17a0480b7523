"""MANO test material: a small MANO-format model built per test module (``mano_dir``, a fixture registered
for every test package in tests/conftest.py) and a right MANO hand over a box."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from common.sequence import HandTrack, ManoParams, ObjectSpec, Sequence
from common.settings import get_settings
from worker.hand.mano import build_test_mano_model

T = 8


@pytest.fixture(scope="module")
def mano_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with MANO_RIGHT.pkl and MANO_LEFT.pkl in the MANO format (small synthetic models; the real ones
    are licensed). Building and reading them needs no torch; decoding with smplx does (those tests skip)."""
    d = tmp_path_factory.mktemp("mano")
    build_test_mano_model(d, "right", seed=0)
    build_test_mano_model(d, "left", seed=0)
    return d


def use_mano_dir(monkeypatch: pytest.MonkeyPatch, mano_dir: Path | None) -> None:
    if mano_dir is None:
        monkeypatch.delenv("HOI_REFINE_MANO_DIR", raising=False)
    else:
        monkeypatch.setenv("HOI_REFINE_MANO_DIR", str(mano_dir))
    get_settings.cache_clear()


def mano_grasp_sequence(frames: int = T) -> Sequence:
    """A right MANO hand (palm down, fingers slightly curled) over a 6 cm box on the table, fingertips
    touching its top; the first frame is invalid."""
    rng = np.random.default_rng(1)
    pose = np.tile(np.abs(rng.normal(0, 0.1, 45)), (frames, 1))
    mano = ManoParams(
        global_orient=np.tile([np.pi, 0.0, 0.0], (frames, 1)), hand_pose=pose,
        trans=np.tile([-0.06, 0.0, 0.075], (frames, 1)), betas=np.array([0.2] + [0.0] * 9),
    )  # fmt: skip
    valid = np.ones(frames, bool)
    valid[0] = False
    return Sequence(
        name="mano-grasp", fps=30.0,
        object=ObjectSpec(name="box", mass_kg=0.1, primitive="box", size=np.array([0.03, 0.03, 0.03])),
        object_pose=np.tile([0.0, 0, 0.03, 1, 0, 0, 0], (frames, 1)),
        hands=[HandTrack(side="right", valid=valid, mano=mano)],
    ).validate()  # fmt: skip
