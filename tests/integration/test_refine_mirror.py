"""A right-hand sequence and its exact mirror image (a left hand; ``common.sequence_mirror``) replay and refine
alike (issue #15 item 5). The control spaces make the two the same optimisation problem sample for sample
(tests/unit/test_sequence_mirror.py), so what remains is MuJoCo's arithmetic, which is not bit-symmetric: the
raw replays agree to a fraction of a millimetre; CMA-ES then amplifies such differences (a candidate ranked
second instead of first), so refined errors are compared within a tolerance, not exactly."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from common.dexycb import load_dexycb_npz
from common.job_options import JobOptions
from common.sequence import Sequence
from common.sequence_mirror import mirror_sequence
from tests.support.synthetic_push import recovery_case
from worker.refine.run import refine_sequence

#: How far the refined errors of a sequence and its mirror may differ (cm, degrees).
E_T_TOLERANCE_CM = 0.3
E_R_TOLERANCE_DEG = 1.0
#: How far the raw replays' errors may differ. Without the noslip pass (issue #19) friction is soft, so the last-bit
#: asymmetry grows a little more in a held object: measured 0.016 cm / 0.08 deg on DEV_RIGHT (0.1 mm with noslip).
RAW_E_T_TOLERANCE_CM = 0.03
RAW_E_R_TOLERANCE_DEG = 0.2
#: A right hand grasping a can (dev40, raw replay already succeeds; the small budget refines a few windows).
DEV_RIGHT = "20200709-subject-01__20200709_141754.npz"


def _both(seq: Sequence, options: JobOptions) -> tuple[dict[str, Any], dict[str, Any]]:
    mirrored = mirror_sequence(seq)
    assert (seq.hands[0].side, mirrored.hands[0].side) == ("right", "left")
    a = refine_sequence(seq, options, threads=2).summary["metrics"]
    b = refine_sequence(mirrored, options, threads=2).summary["metrics"]
    return a, b


def _assert_alike(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert abs(a["raw"]["E_t"] - b["raw"]["E_t"]) < RAW_E_T_TOLERANCE_CM, (a["raw"], b["raw"])
    assert abs(a["raw"]["E_r"] - b["raw"]["E_r"]) < RAW_E_R_TOLERANCE_DEG, (a["raw"], b["raw"])
    ra, rb = a["refined"], b["refined"]
    assert ra["success"] and rb["success"], (ra, rb)
    assert abs(ra["E_t"] - rb["E_t"]) <= E_T_TOLERANCE_CM, (ra, rb)
    assert abs(ra["E_r"] - rb["E_r"]) <= E_R_TOLERANCE_DEG, (ra, rb)


@pytest.mark.slow
def test_a_synthetic_push_and_its_mirror_refine_alike() -> None:
    # The shifted push of the recovery test (the raw replay fails; refinement must move the wrist forward,
    # through the free translation, which the mirror reflects too).
    seq, _ = recovery_case()
    a, b = _both(seq, JobOptions(seed=7, popsize=12, max_generations=8, free_wrist_translation=True, restarts=0))
    assert not a["raw"]["success"] and not b["raw"]["success"]
    _assert_alike(a, b)


@pytest.mark.slow
def test_a_dexycb_right_hand_and_its_mirror_refine_alike(dexycb_dev_files: list[Path]) -> None:
    path = next((f for f in dexycb_dev_files if f.name == DEV_RIGHT), None)
    if path is None:
        pytest.skip(f"{DEV_RIGHT} is not in the dev data")
    a, b = _both(load_dexycb_npz(path), JobOptions(seed=3, popsize=6, max_generations=2, restarts=0))
    _assert_alike(a, b)


def test_verify_re_simulates_a_left_hand_with_the_controls_it_was_made_with(monkeypatch: pytest.MonkeyPatch) -> None:
    """Results made before left hands were mirrored record no ``left_hand_controls`` and verify as made; a
    convention other than the current one is a config change (``--allow-config``)."""
    import worker.refine.prepare as prepare_module
    from common.errors import ResultMismatchError
    from worker.refine.result import verify_result
    from worker.refine.run import RefineOutcome

    seq, _ = recovery_case(frames=16)
    left = mirror_sequence(seq)
    options = JobOptions(seed=1, popsize=4, max_generations=1, restarts=0)
    with monkeypatch.context() as m:
        m.setattr(prepare_module, "MIRROR_LEFT_HAND", False)  # the old treatment of left hands
        old = refine_sequence(left, options)
    assert old.summary["config"]["left_hand_controls"] == "as right"
    assert abs(old.keyframes["left"]).max() > 0  # something was optimised, so the convention matters
    unrecorded = {**old.summary, "config": {k: v for k, v in old.summary["config"].items()
                                            if k != "left_hand_controls"}}
    verify_result(RefineOutcome(old.arrays, unrecorded).to_npz_bytes())
    with pytest.raises(ResultMismatchError, match="left_hand_controls"):
        verify_result(old.to_npz_bytes())  # recorded, not the default: a config change
    verify_result(old.to_npz_bytes(), allow_config=True)
    as_if_new = {**old.summary, "config": {**old.summary["config"], "left_hand_controls": "mirrored"}}
    with pytest.raises(ResultMismatchError):
        verify_result(RefineOutcome(old.arrays, as_if_new).to_npz_bytes())
    new = refine_sequence(left, options)
    assert new.summary["config"]["left_hand_controls"] == "mirrored"
    verify_result(new.to_npz_bytes())
