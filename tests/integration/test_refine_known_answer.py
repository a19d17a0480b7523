"""A known answer for the default parameterisation (issue #15 item 7): 10 pose-basis coefficients and the wrist
rotation, no free translation. The recorded object is what a known hand motion does in simulation (the built-in
grasp-and-lift, closed and turned so that it lifts the box 20 cm); the refinement starts from controls moved away
from that motion by a known pose and rotation offset (``known_answer_case``) and must bring the object and the
controls back.

What it shows (fixed seeds, a small budget): the object comes back to within a few millimetres and a degree,
and the controls come back towards the known ones (wrist, hinge targets), but not all the way. The coordinates
are not all identifiable from the object track and the keypoints alone, and the greedy window loop does not find
the truth even where the truth is better on every term: with the product budget (popsize 10, 10 generations),
the same case ends with the object as close (E_t 0.20 cm, E_r 0.84 deg) but the wrist turned 12.6 deg from the
truth (6.2 deg at the start) and E_j 0.81 cm, where the truth's own replay has E_t 0.01 cm, E_r 0.17 deg,
E_j 0.20 cm (measured on the branch that added this test)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from common.job_options import JobOptions
from tests.integration.test_refine_synthetic import known_answer_case
from worker.metrics import compute_metrics
from worker.refine.evaluator import ParallelEvaluator
from worker.refine.prepare import initial_state
from worker.refine.run import RefineOutcome, refine_sequence, replay

BUDGET = JobOptions(seed=1, popsize=8, max_generations=4, restarts=0)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.asarray(np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=1)), 0.0, 1.0))))


@pytest.fixture(scope="module")
def case() -> tuple[Any, Any, np.ndarray, RefineOutcome]:
    seq, prep, truth = known_answer_case(BUDGET)
    return seq, prep, truth, refine_sequence(seq, BUDGET, threads=2, prepared=prep)


@pytest.mark.slow
def test_the_known_controls_reproduce_the_recorded_object(case: tuple[Any, Any, np.ndarray, RefineOutcome]) -> None:
    _, prep, truth, _ = case
    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = initial_state(prep, ev)
        rec = replay(prep, ev, start, {"right": truth}, False)
    m = compute_metrics(rec.object_pose, prep.obj_targets_pose(), rec.keypoints,
                        {r.side: r.keypoints for r in prep.references}, {r.side: r.valid for r in prep.references})
    lift = prep.obj_targets.pos[:, 2].max() - prep.obj_targets.pos[0, 2]
    assert lift > 0.15  # a real lift, held by the hand
    assert m["E_t"] < 0.05 and m["E_r"] < 0.5, m  # the answer is an answer (cm, deg)


@pytest.mark.slow
def test_refinement_from_a_perturbed_start_recovers_object_and_controls(
    case: tuple[Any, Any, np.ndarray, RefineOutcome],
) -> None:
    _, prep, truth, outcome = case
    raw, refined = outcome.summary["metrics"]["raw"], outcome.summary["metrics"]["refined"]
    assert raw["E_r"] > 5.0  # the perturbed start turns the held box
    assert refined["success"]
    assert refined["E_t"] <= 0.5 and refined["E_r"] <= 1.5, refined
    assert outcome.summary["config"]["free_wrist_translation"] is False
    space = prep.spaces["right"]
    q_true, p_true, r_true = space.frame_controls(truth)
    q_start, p_start, r_start = space.frame_controls(space.zero_keyframes())
    q_ref, p_ref, r_ref = space.frame_controls(outcome.keyframes["right"])

    def errors(q: np.ndarray, p: np.ndarray, r: np.ndarray) -> tuple[float, float, float]:
        return (float(np.sqrt(np.mean((q - q_true) ** 2))), float(np.linalg.norm(p - p_true, axis=1).mean()),
                float(_angle_deg(r, r_true).mean()))

    (q0, p0, r0), (q1, p1, r1) = errors(q_start, p_start, r_start), errors(q_ref, p_ref, r_ref)
    assert r0 > 5.0  # the start is 6 deg off
    assert q1 < 0.85 * q0, (q0, q1)  # hinge targets (rad RMS)
    assert p1 < 0.7 * p0, (p0, p1)  # wrist position (m), moved only through the rotation about the pivot
    assert r1 < 0.8 * r0, (r0, r1)  # wrist rotation (deg)
