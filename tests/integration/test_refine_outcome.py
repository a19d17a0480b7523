"""A result's outcome and its reasons on crafted synthetic sequences, and the bounded tail (issue #53 items 2-3):
a recording that jumps, an object that falls before the hand arrives, a hand that never touches, fingers through
the object, a hand annotated in few frames, an executable replay, and the plan cut short by a reason or by the
evaluation budget."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from common.geometry import quat_mul
from common.job_options import JobOptions
from common.outcome import Outcome, ReasonCode
from common.result_format import read_arrays, read_summary, write_result_npz
from common.sequence import Sequence
from worker.example.sequences import example_sequence, short_example_sequence
from worker.refine.derive import replay_metrics
from worker.refine.evaluator import ParallelEvaluator
from worker.refine.outcome import (
    FINGERS_THROUGH_MM,
    classify_outcome,
    fingers_through_object,
    hand_sparse,
    recorded_depth,
    recording_too_fast,
    unsupported_start,
)
from worker.refine.prepare import Prepared, prepare, settled_start
from worker.refine.replay import replay
from worker.refine.result import verify_result
from worker.refine.run import refine_sequence
from worker.simulation.metrics import compute_metrics
from worker.verification import check_result

#: A budget that runs in seconds: the outcome does not depend on how well the grasp is refined.
QUICK: dict[str, Any] = {"max_generations": 2, "popsize": 4}
JUMP_FRAME = 15


def _jumping(seq: Sequence, frame: int = JUMP_FRAME, deg: float = 90.0) -> Sequence:
    """``seq`` with its recorded object turned by ``deg`` about the vertical from ``frame`` on (a pose-fit jump)."""
    half = np.radians(deg) / 2
    turn = np.array([np.cos(half), 0.0, 0.0, np.sin(half)])
    seq.object_pose[frame:, 3:] = np.array([quat_mul(q, turn) for q in seq.object_pose[frame:, 3:]])
    return seq


def _raw_outcome(seq: Sequence) -> tuple[Prepared, Outcome]:
    """The outcome of the raw replay (zero offsets): the classifier on a replay with contacts, no optimisation."""
    prep = prepare(seq, JobOptions())
    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = settled_start(prep, ev)
        rec = replay(prep, ev, start, {s: sp.zero_keyframes() for s, sp in prep.spaces.items()})
    assert rec.contact_frames is not None
    metrics = replay_metrics(prep, rec)
    return prep, classify_outcome(prep, metrics, rec.object_pose, hand_contact=rec.contact_frames.hand)


def test_a_recording_that_jumps_is_too_fast_and_the_plan_stops_after_the_first_attempt() -> None:
    out = refine_sequence(_jumping(short_example_sequence()), JobOptions(**QUICK, tail="bounded"))
    outcome = Outcome.model_validate(out.summary["outcome"])
    assert not outcome.executable
    first = outcome.reasons[0]
    assert first.code == ReasonCode.RECORDING_TOO_FAST and first.frame == JUMP_FRAME and first.unit == "deg/frame"
    assert first.value == pytest.approx(90.0, abs=2.0)
    # The rest of the plan (restarts, polish, rescue) is skipped, and the result says so.
    assert len(out.summary["attempts"]) == 1
    cut = [r for r in outcome.reasons if r.code == ReasonCode.PLAN_CUT_SHORT]
    assert len(cut) == 1 and cut[0].value == out.summary["timings"]["evaluations"] and cut[0].unit == "evaluations"
    # verify recomputes the outcome from the embedded sequence and the stored controls: a forged one fails.
    blob = out.to_npz_bytes()
    verify_result(blob)
    arrays, summary = read_arrays(blob), read_summary(blob)
    summary["outcome"]["reasons"][0]["frame"] = JUMP_FRAME + 5
    summary["outcome"]["reasons"][-1]["value"] = 1.0
    failures = check_result(write_result_npz(arrays, summary)).failures
    assert any(f.startswith("outcome.reasons[0].frame") for f in failures), failures
    assert any("plan_cut_short says 1.0 evaluations" in f for f in failures), failures


def test_the_full_tail_runs_the_plan_and_an_evaluation_budget_cuts_it() -> None:
    seq = _jumping(short_example_sequence())
    full = refine_sequence(seq, JobOptions(**QUICK, restarts=1, polish=False))  # the default: the full plan
    assert len(full.summary["attempts"]) == 2
    assert ReasonCode.PLAN_CUT_SHORT not in Outcome.model_validate(full.summary["outcome"]).codes
    budget = refine_sequence(seq, JobOptions(**QUICK, restarts=2, polish=False, evaluation_budget=1))
    assert len(budget.summary["attempts"]) == 1
    reasons = Outcome.model_validate(budget.summary["outcome"]).reasons
    cut = [r for r in reasons if r.code == ReasonCode.PLAN_CUT_SHORT]
    assert len(cut) == 1 and "budget" in cut[0].message
    # A plan of one run has nothing to cut: the bounded tail claims no cut there.
    single = refine_sequence(seq, JobOptions(**QUICK, tail="bounded", restarts=0, polish=False))
    assert ReasonCode.PLAN_CUT_SHORT not in Outcome.model_validate(single.summary["outcome"]).codes


def test_a_recording_without_a_jump_is_not_too_fast() -> None:
    prep = prepare(short_example_sequence(), JobOptions())
    assert recording_too_fast(prep) is None


def _on_its_edge(seq: Sequence) -> Sequence:
    """``seq`` with the box recorded standing on one edge, 45 deg over, its centre of mass beside the edge."""
    c, s = np.cos(np.pi / 8), np.sin(np.pi / 8)
    tilt = np.array([c, s, 0.0, 0.0])  # 45 deg about x
    half = np.asarray(seq.object.size)
    rot = np.array([[1, 0, 0], [0, np.cos(np.pi / 4), -np.sin(np.pi / 4)], [0, np.sin(np.pi / 4), np.cos(np.pi / 4)]])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
    low = float((corners @ rot.T)[:, 2].min())
    pose = seq.object_pose
    pose[:, 3:] = np.array([quat_mul(q, tilt) for q in pose[:, 3:]])
    pose[:, 2] += -low - float(half[2])  # the lowest edge on the table (the box stood on its face at z = half)
    return seq


def test_an_object_standing_on_its_edge_falls_before_the_hand_arrives() -> None:
    prep, outcome = _raw_outcome(_on_its_edge(example_sequence()))
    reason = unsupported_start(prep)
    assert reason is not None and reason.code == ReasonCode.UNSUPPORTED_START
    assert reason.frame is not None and 0 < reason.frame < 22  # the recorded hand reaches the box at about 22
    assert reason.value is not None and reason.value > 1.0 and reason.unit in ("cm", "deg")
    assert not outcome.executable and ReasonCode.UNSUPPORTED_START in outcome.codes
    # The upright box stays where it is recorded.
    assert unsupported_start(prepare(example_sequence(), JobOptions())) is None


def _hand_moved(seq: Sequence, offset: tuple[float, float, float]) -> Sequence:
    for hand in seq.hands:
        assert hand.keypoints is not None
        hand.keypoints[:] = hand.keypoints + np.asarray(offset)
    return seq


def test_a_hand_that_never_touches_has_no_contact() -> None:
    _, outcome = _raw_outcome(_hand_moved(short_example_sequence(), (0.3, 0.0, 0.0)))
    assert not outcome.executable
    first = outcome.reasons[0]
    assert first.code == ReasonCode.NO_CONTACT and first.unit == "cm"
    assert first.value is not None and first.value > 15.0  # the hand passes 30 cm beside the 5.6 cm box


def test_recorded_fingers_inside_the_object_pass_through_it() -> None:
    prep = prepare(short_example_sequence(), JobOptions())
    depth, _ = recorded_depth(prep)
    assert depth <= FINGERS_THROUGH_MM  # the example's fingers sink 4 mm and a few more by its observation errors
    assert fingers_through_object(prep) is None
    # The fingers gathered around the box's centre (a tenth of their spread): 2.8 cm from its nearest face.
    seq = short_example_sequence()
    for hand in seq.hands:
        assert hand.keypoints is not None
        fingers = hand.keypoints[:, 1:]
        centre = fingers.mean(axis=1, keepdims=True)
        hand.keypoints[:, 1:] = seq.object_pose[:, None, :3] + 0.1 * (fingers - centre)
    prep = prepare(seq, JobOptions())
    depth, frame = recorded_depth(prep)
    assert depth > FINGERS_THROUGH_MM and 0 <= frame < seq.num_frames
    reason = fingers_through_object(prep)
    assert reason is not None and reason.code == ReasonCode.FINGERS_THROUGH_OBJECT and reason.unit == "mm"
    assert reason.value == pytest.approx(depth, abs=0.1)


def test_an_executable_result_has_no_reasons_but_a_rescue() -> None:
    # The clean example replayed without refinement never lifts the box (the servos press too little): the
    # classifier says so; a replay that follows the recording exactly is executable and has nothing to say.
    prep, raw = _raw_outcome(example_sequence(errors=False))
    assert not raw.executable and raw.reasons[0].code == ReasonCode.NOT_LIFTED
    recorded = prep.obj_targets_pose()
    keypoints = {r.side: r.keypoints for r in prep.references}
    exact = compute_metrics(recorded, recorded, keypoints, keypoints, {r.side: r.valid for r in prep.references})
    touching = np.ones(prep.num_frames, dtype=bool)
    outcome = classify_outcome(prep, exact, recorded, hand_contact=touching)
    assert outcome.executable and outcome.reasons == []
    rescued = classify_outcome(prep, exact, recorded, hand_contact=touching, rescued=True)
    assert rescued.executable and rescued.codes == [ReasonCode.RESCUED_ON_FINER_PARTS]


def test_a_hand_annotated_in_few_frames_is_sparse() -> None:
    seq = short_example_sequence()
    seq.hands[0].valid[6:20] = False  # annotated in 10 of 24 frames, the longest gap from frame 6
    reason = hand_sparse(prepare(seq, JobOptions()))
    assert reason is not None and reason.code == ReasonCode.HAND_SPARSE
    assert reason.frame == 6 and reason.unit == "fraction" and reason.value == pytest.approx(10 / 24, abs=1e-3)
    assert hand_sparse(prepare(short_example_sequence(), JobOptions())) is None
