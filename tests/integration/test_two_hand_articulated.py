"""The built-in two-handed articulated example end to end (issue #52 "must show"): the hinged box refines to
success with both hands driven and its lid opened by contact, the result verifies bit for bit, contacts name the
hand and the part, and both two-hand modes run."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from common.job_options import JobOptions
from common.result_format import read_arrays, read_summary
from worker.example.hinged_box import short_hinged_box_sequence
from worker.refine.run import RefineOutcome, object_error, refine_sequence
from worker.simulation.replay import raw_replay
from worker.verification import verify_result


@pytest.fixture(scope="module")
def refined() -> RefineOutcome:
    return refine_sequence(short_hinged_box_sequence(), JobOptions(), threads=2)


def test_the_raw_replay_opens_the_lid_only_through_contact() -> None:
    seq = short_hinged_box_sequence(errors=False)
    result = raw_replay(seq)
    assert result.record.articulation is not None and seq.articulation is not None
    opened = result.record.articulation[-1, 0]
    assert opened > 0.5, opened  # the right hand swung it open: nothing else drives the joint
    # Without the hands the lid stays shut: the joint's friction holds it against gravity.
    assert result.record.articulation[0, 0] == pytest.approx(seq.articulation[0, 0], abs=0.02)


@pytest.mark.slow
def test_the_hinged_box_refines_to_success_and_verifies(refined: RefineOutcome) -> None:
    summary = refined.summary
    m = summary["metrics"]["refined"]
    assert m["success"] and m["paper"]["success"], m
    assert m["E_a"] < 5.0 and m["E_t"] < 1.0, m
    assert set(m["per_hand"]) == {"right", "left"}
    blob = refined.to_npz_bytes()
    report = verify_result(blob)
    assert report["exact"] and report["max_pos_diff_m"] == 0.0
    arrays = read_arrays(blob)
    assert set(arrays["contact_hand"]) == {"right", "left"}
    touched: dict[str, set[str]] = {}
    for hand, part in zip(arrays["contact_hand"], arrays["contact_part"], strict=True):
        touched.setdefault(str(hand), set()).add(str(part))
    assert "lid" in touched["right"] and "base" in touched["left"], touched
    assert arrays["object_articulation_sim"].shape == (len(arrays["object_pose_sim"]), 1)


def test_both_hands_and_the_lid_are_checked_stepwise(refined: RefineOutcome) -> None:
    """The stored integration state holds both hands and the object's joints (issue #54): the result verifies
    stepwise, and a lid swung open in the stored states alone fails naming the lid's joint and the frame."""
    import mujoco

    from common.errors import ResultMismatchError
    from common.result_format import write_result_npz
    from worker.refine.result import prepare_from_result
    from worker.verification import check_result
    from worker.verification.stepwise import StateLayout

    blob = refined.to_npz_bytes(wall_clock=False)
    report = check_result(blob)
    assert report.failures == [] and report.method == "stepwise"
    assert all(r.exact and r.frames == refined.summary["frames"] for r in report.stepwise.values())
    prep, _ = prepare_from_result(blob)
    model = prep.layout.model
    layout = StateLayout(model)
    arrays: dict[str, Any] = read_arrays(blob)
    assert {layout.entry("ctrl", i).split("_")[0] for i in range(model.nu)} == {"right", "left"}
    adr = int(prep.scene.object_joint_qpos_adr[0])
    joint = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, int(np.flatnonzero(model.jnt_qposadr == adr)[0]))
    states = arrays["state_sim"].copy()
    frame = len(states) // 2
    states[frame:, layout.slices["qpos"].start + adr] += np.radians(3.0)
    arrays["state_sim"] = states
    arrays["object_articulation_sim"] = arrays["object_articulation_sim"].copy()
    arrays["object_articulation_sim"][frame:] += np.radians(3.0)
    forged = write_result_npz(arrays, read_summary(blob))
    with pytest.raises(ResultMismatchError, match=f"state_sim.qpos: .* at frame {frame} \\({joint};"):
        verify_result(forged)


@pytest.mark.slow
def test_a_forged_joint_track_fails_verify(refined: RefineOutcome) -> None:
    from common.errors import ResultMismatchError
    from common.result_format import write_result_npz

    arrays: dict[str, Any] = read_arrays(refined.to_npz_bytes())
    arrays["object_articulation_sim"] = arrays["object_articulation_sim"] + np.radians(3.0)
    forged = write_result_npz(arrays, read_summary(refined.to_npz_bytes()))
    with pytest.raises(ResultMismatchError, match="object_articulation_sim"):
        verify_result(forged)


@pytest.mark.slow
def test_one_cma_es_over_both_hands_also_refines_the_example() -> None:
    outcome = refine_sequence(short_hinged_box_sequence(), JobOptions(two_hands="joint", restarts=0, polish=False),
                              threads=2)
    assert outcome.summary["metrics"]["refined"]["success"], outcome.summary["metrics"]["refined"]
    assert {"right_keyframes", "left_keyframes"} <= set(outcome.arrays)


def test_a_failed_attempt_is_repaired_locally_and_the_result_verifies(monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``local_repair`` the polish of a two-handed articulated sequence is the local repair: with the
    position limit tightened to 0.8 cm the example's cheap single attempt fails; the repair re-optimises the
    windows around its first failing frame, is listed among the attempts, ranks higher, and verifies exactly."""
    import worker.refine.outcome as outcome
    import worker.simulation.metrics as metrics

    monkeypatch.setattr(metrics, "SUCCESS_POSITION_CM", 0.8)
    monkeypatch.setattr(outcome, "SUCCESS_POSITION_CM", 0.8)

    out = refine_sequence(short_hinged_box_sequence(), JobOptions(restarts=0, max_generations=1, popsize=2,
                                                                     local_repair=True), threads=1)
    first, *rest = out.summary["attempts"]
    assert not first["success"] and len(rest) == 1 and rest[0]["repair"]["kept"] >= 1, out.summary["attempts"]
    refined = out.summary["metrics"]["refined"]
    assert (refined["E_t"], refined["E_r"]) == (rest[0]["E_t"], rest[0]["E_r"])
    assert object_error(rest[0]) < object_error(first)
    report = verify_result(out.to_npz_bytes())
    assert report["exact"], report
