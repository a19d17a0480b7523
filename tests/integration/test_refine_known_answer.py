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

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from common.job_options import JobOptions
from tests.support.synthetic_push import known_answer_case
from worker.refine.derive import replay_metrics
from worker.refine.evaluator import ParallelEvaluator
from worker.refine.losses import resolve_weights
from worker.refine.prepare import Prepared, settled_start
from worker.refine.replay import replay, window_problem
from worker.refine.run import cma_settings
from worker.refine.windowed import optimise_windows

BUDGET = JobOptions(seed=1, popsize=8, max_generations=4, restarts=0)


@dataclass
class Case:
    prep: Prepared
    truth: np.ndarray  # (K, 13) the known keyframes
    truth_metrics: dict[str, Any]  # the known keyframes replayed
    raw: dict[str, Any]  # zero keyframes (the perturbed start) replayed
    refined: dict[str, Any]
    keyframes: np.ndarray


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.asarray(np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=1)), 0.0, 1.0))))


@pytest.fixture(scope="module")
def case() -> Case:
    """The refinement's window loop (``refine_sequence`` without restarts and without the result's derivation,
    which would re-prepare the unperturbed sequence) on the perturbed problem."""
    _, prep, truth = known_answer_case(BUDGET)
    with ParallelEvaluator(prep.scene.model, 2) as ev:
        start, _ = settled_start(prep, ev)
        problem = window_problem(prep, ev, start, resolve_weights(BUDGET.loss_weights))
        keyframes, _ = optimise_windows(problem, cma_settings(BUDGET, prep.interval))
        zero = {"right": prep.spaces["right"].zero_keyframes()}
        figures = [replay_metrics(prep, replay(prep, ev, start, k, record_contacts=False))
                   for k in ({"right": truth}, zero, keyframes)]
    return Case(prep, truth, *figures, keyframes["right"])


@pytest.mark.slow
def test_the_known_controls_reproduce_the_recorded_object(case: Case) -> None:
    lift = case.prep.obj_targets.pos[:, 2].max() - case.prep.obj_targets.pos[0, 2]
    assert lift > 0.15  # a real lift, held by the hand
    m = case.truth_metrics
    assert m["E_t"] < 0.05 and m["E_r"] < 0.5, m  # the answer is an answer (cm, deg)


@pytest.mark.slow
def test_refinement_from_a_perturbed_start_recovers_object_and_controls(case: Case) -> None:
    assert case.raw["E_r"] > 5.0  # the perturbed start turns the held box
    refined = case.refined
    assert refined["success"]
    assert refined["E_t"] <= 0.5 and refined["E_r"] <= 1.5, refined
    space = case.prep.spaces["right"]
    assert space.dim == 13  # 10 pose coefficients + wrist rotation, no free translation
    q_true, p_true, r_true = space.frame_controls(case.truth)
    q_start, p_start, r_start = space.frame_controls(space.zero_keyframes())
    q_ref, p_ref, r_ref = space.frame_controls(case.keyframes)

    def errors(q: np.ndarray, p: np.ndarray, r: np.ndarray) -> tuple[float, float, float]:
        return (float(np.sqrt(np.mean((q - q_true) ** 2))), float(np.linalg.norm(p - p_true, axis=1).mean()),
                float(_angle_deg(r, r_true).mean()))

    (q0, p0, r0), (q1, p1, r1) = errors(q_start, p_start, r_start), errors(q_ref, p_ref, r_ref)
    assert r0 > 5.0  # the start is 6 deg off
    assert q1 < 0.85 * q0, (q0, q1)  # hinge targets (rad RMS)
    assert p1 < 0.7 * p0, (p0, p1)  # wrist position (m), moved only through the rotation about the pivot
    assert r1 < 0.8 * r0, (r0, r1)  # wrist rotation (deg)
