"""The penetration loss term (issue #15 item 4): the contact sensor every rollout records reads the same depth
as the metric's per-frame penetration (from ``data.contact``), and the term costs only when weighted and only
on the frames where the rollout's object is lifted."""

from __future__ import annotations

import mujoco
import numpy as np

from common.job_options import JobOptions
from tests.support.synthetic_push import push_sequence
from worker.refine.evaluator import ParallelEvaluator
from worker.refine.losses import resolve_weights
from worker.refine.prepare import prepare, settled_start
from worker.refine.problem import SimWindowProblem
from worker.refine.replay import replay


def test_penetration_sensor_matches_the_metrics_contact_depth() -> None:
    seq = push_sequence(frames=24)
    prep = prepare(seq, JobOptions())
    hand = prep.layout.hands["right"]
    assert hand.penetration_sensor_adr >= 0
    s = prep.layout.substeps
    sensed = np.zeros(prep.num_frames)

    def at_frames(i: int, d: mujoco.MjData) -> None:
        if i % s == 0:
            sensed[i // s] = float(hand.penetration(np.asarray(d.sensordata)))

    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = settled_start(prep, ev)
        kf = {side: sp.zero_keyframes() for side, sp in prep.spaces.items()}
        rec = replay(prep, ev, start, kf, on_step=at_frames)
    assert rec.contact_frames is not None
    metric = rec.contact_frames.penetration_m
    assert metric.max() > 1e-4, "the push must press the hand into the box for this test to mean anything"
    np.testing.assert_allclose(sensed, metric, atol=1e-12)


def test_penetration_term_is_recorded_weighted_and_charged_only_while_the_object_is_lifted() -> None:
    seq = push_sequence(frames=24)
    prep = prepare(seq, JobOptions())
    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = settled_start(prep, ev)
        kf = {side: sp.zero_keyframes() for side, sp in prep.spaces.items()}
        cand = {"right": np.random.default_rng(0).normal(scale=0.3, size=(3, prep.spaces["right"].dim))}
        resting, lifted, pen, f0, f1 = {}, {}, np.zeros(0), 0, 0
        for weight in (0.0, 2.0):
            problem = SimWindowProblem(prep.layout, prep.spaces, prep.obj_targets, prep.hand_targets,
                                       resolve_weights({"penetration": weight}), ev, start)
            j = 0  # frames 1-10: the hand pushes the box along the table from frame 1 on
            f0, f1 = problem.window(j)
            control, offsets = problem.build_control(kf, f0, f1, j, cand)
            states, sensors = ev.rollout(start, control)
            rec = problem._record(f0, f1, states, sensors, offsets)
            assert rec.lifted is not None and not rec.lifted.any(), "the pushed box stays on the table"
            resting[weight] = problem.evaluate(j, start, kf, cand)["right"]
            problem._rest_z = -np.inf  # as if the box were carried: every frame is charged
            lifted[weight] = problem.evaluate(j, start, kf, cand)["right"]
            pen = problem._record(f0, f1, states, sensors, offsets).penetration["right"]  # (C, F) m
    assert pen.shape == (3, f1 - f0) and pen.max() > 1e-4
    # A resting object: the hand pressing into it costs nothing (the grip forms freely) ...
    np.testing.assert_array_equal(resting[2.0], resting[0.0])
    # ... a lifted one: the same rollouts, so the difference is exactly 2 * sum over frames of (depth / 1 mm)^2.
    np.testing.assert_allclose(lifted[2.0] - lifted[0.0], 2.0 * ((pen / 1e-3) ** 2).sum(axis=1), rtol=1e-9)


def test_penetration_term_is_the_square_of_the_depth_in_millimetres_summed_over_frames() -> None:
    from worker.refine.losses import HandKeypointTargets, WindowRecord, hand_terms

    c, f, j = 3, 4, 21
    depth = np.array([[0.0] * f, [0.0005] * f, [0.0, 0.0, 0.0, 0.003]])
    rec = WindowRecord(frames=np.arange(f), obj_pos=np.zeros((c, f, 3)), obj_quat=np.tile([1.0, 0, 0, 0], (c, f, 1)),
                       obj_vel=np.zeros((c, f, 6)), keypoints={"right": np.zeros((c, f, j, 3))},
                       hinge_vel={"right": np.zeros((c, f, 45))}, offsets={"right": np.zeros((c, f + 1, 2))},
                       penetration={"right": depth})
    ref = HandKeypointTargets(np.zeros((f, j, 3)), np.ones(f, dtype=bool), (4, 8, 12, 16, 20),
                              np.zeros((f, 5), dtype=bool), np.zeros((f, 5, 3)))
    np.testing.assert_allclose(hand_terms(rec, "right", ref)["penetration"], [0.0, 0.25 * f, 9.0])
    # Only the frames where the rollout's object is lifted count.
    rec.lifted = np.array([[True] * f, [False, True, False, True], [True, True, True, False]])
    np.testing.assert_allclose(hand_terms(rec, "right", ref)["penetration"], [0.0, 0.25 * 2, 0.0])
    # Without a recorded penetration (a model without the sensor) the term is zero.
    rec.penetration = {}
    np.testing.assert_allclose(hand_terms(rec, "right", ref)["penetration"], 0.0)
