"""Unit tests of the refinement core on a tiny inline MJCF (DESIGN §4 style): spline, controls, evaluator,
window loop. The full pipeline on the built-in hand is tested in tests/integration/test_refine_*.py."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from common.geometry import quat_exp, quat_mul, quat_rotate
from worker.refine.controls import HandControlSpace, PoseBasis10
from worker.refine.evaluator import ParallelEvaluator, SimState
from worker.refine.losses import HandKeypointTargets, ObjectTargets, finite_difference_velocity, resolve_weights
from worker.refine.problem import SimLayout, SimWindowProblem
from worker.refine.spline import (
    catmull_rom_weights,
    default_keyframe_interval,
    keyframe_window,
    num_keyframes,
)
from worker.refine.windowed import CmaSettings, optimise_windows

# A "hand" of a palm paddle (welded to a mocap body) with two hinged fingers, pushing a box on a table.
TINY = """
<mujoco>
  <option timestep="0.004166666666666667" integrator="implicitfast" iterations="10" noslip_iterations="10"/>
  <worldbody>
    <geom name="table" type="plane" size="1 1 0.01" contype="4" conaffinity="2"/>
    <body name="right_mocap" mocap="true" pos="-0.035 0 0.03"/>
    <body name="right_palm" pos="-0.035 0 0.03">
      <freejoint name="right_root"/>
      <geom type="box" size="0.01 0.04 0.02" contype="1" conaffinity="2" density="1000"/>
      <site name="right_kp0"/>
      <body pos="0 0.03 0.02">
        <joint name="right_h0" type="hinge" axis="0 1 0" range="-1 1"/>
        <geom type="capsule" fromto="0 0 0 0.04 0 0" size="0.005" contype="1" conaffinity="2"/>
        <site name="right_kp1" pos="0.04 0 0"/>
      </body>
      <body pos="0 -0.03 0.02">
        <joint name="right_h1" type="hinge" axis="0 1 0" range="-1 1"/>
        <geom type="capsule" fromto="0 0 0 0.04 0 0" size="0.005" contype="1" conaffinity="2"/>
        <site name="right_kp2" pos="0.04 0 0"/>
      </body>
    </body>
    <body name="object" pos="0 0 0.02">
      <freejoint/>
      <geom type="box" size="0.02 0.02 0.02" mass="0.1" contype="2" conaffinity="5"/>
    </body>
  </worldbody>
  <equality><weld body1="right_mocap" body2="right_palm" relpose="0 0 0 1 0 0 0"/></equality>
  <actuator>
    <position name="right_h0" joint="right_h0" kp="5" kv="0.3"/>
    <position name="right_h1" joint="right_h1" kp="5" kv="0.3"/>
  </actuator>
  <sensor>
    <framepos name="right_kp0" objtype="site" objname="right_kp0"/>
    <framepos name="right_kp1" objtype="site" objname="right_kp1"/>
    <framepos name="right_kp2" objtype="site" objname="right_kp2"/>
    <framepos name="object_pos" objtype="body" objname="object"/>
    <framequat name="object_quat" objtype="body" objname="object"/>
    <framelinvel name="object_linvel" objtype="body" objname="object"/>
    <frameangvel name="object_angvel" objtype="body" objname="object"/>
  </sensor>
</mujoco>
"""
FPS, SUBSTEPS, FRAMES = 30.0, 8, 21


def tiny_setup(push: float = 0.03) -> tuple[SimLayout, HandControlSpace, SimState]:
    model = mujoco.MjModel.from_xml_string(TINY)
    layout = SimLayout.from_model(model, ["right"], ["h0", "h1"], "object", SUBSTEPS, n_keypoints=3)
    t = np.arange(FRAMES) / (FRAMES - 1)
    wrist = np.stack([-0.035 + push * t, np.zeros(FRAMES), np.full(FRAMES, 0.03)], axis=1)
    quat = np.tile([1.0, 0, 0, 0], (FRAMES, 1))
    # Only the 10 PCA coordinates are irrelevant here (2 hinges); the wrist rotation is what moves the box.
    basis = PoseBasis10(np.zeros((10, 2)), np.ones(10))
    space = HandControlSpace("right", np.zeros((FRAMES, 2)), wrist, quat, np.array([[-1.0, 1], [-1, 1]]), basis,
                             interval=5, substeps=SUBSTEPS)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return layout, space, SimState.capture(model, data)


def test_keyframe_interval_and_count() -> None:
    assert default_keyframe_interval(30.0) == 5
    assert default_keyframe_interval(60.0) == 10
    assert num_keyframes(72, 5) == 16  # 0, 5, ..., 75 >= 71
    assert keyframe_window(0, 16, 5, 72) == (0, 5)
    assert keyframe_window(5, 16, 5, 72) == (15, 30)
    assert keyframe_window(15, 16, 5, 72) == (65, 71)


def test_catmull_rom_interpolates_keyframes_with_local_support() -> None:
    w = catmull_rom_weights(np.arange(0, 31, dtype=float), 5, 7)
    rng = np.random.default_rng(0)
    p = rng.normal(size=(7, 3))
    np.testing.assert_allclose((w @ p)[::5], p, atol=1e-12)
    # Keyframe 3 shapes only the segments starting at keyframes 1..4 (frames 5..25).
    support = np.flatnonzero(np.abs(w[:, 3]) > 0)
    assert support.min() > 5 and support.max() < 25


def test_quaternion_helpers() -> None:
    q = quat_exp(np.array([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(q, [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)], atol=1e-12)
    np.testing.assert_allclose(quat_mul(q, q), [0, 0, 0, 1], atol=1e-12)


def test_controls_shape_errors_name_the_argument() -> None:
    _, space, _ = tiny_setup()
    with pytest.raises(ValueError, match="keyframes"):
        space.offsets(np.zeros((2, 13)), np.arange(10))
    with pytest.raises(ValueError, match="q_limits"):
        HandControlSpace("right", np.zeros((5, 2)), np.zeros((5, 3)), np.tile([1.0, 0, 0, 0], (5, 1)),
                         np.zeros((3, 2)), PoseBasis10(np.zeros((10, 2)), np.ones(10)), 5, 8)


def test_a_rotation_offset_turns_the_hand_about_the_pivot() -> None:
    _, plain, _ = tiny_setup()
    centre = plain.wrist_pos + np.array([0.08, 0.0, 0.0])  # a grasp centre 8 cm ahead of the wrist
    pivoted = HandControlSpace("right", plain.q_ref, plain.wrist_pos, plain.wrist_quat, plain.q_limits, plain.basis,
                               interval=5, substeps=SUBSTEPS, pivot=centre)
    idx = np.arange(FRAMES) * SUBSTEPS
    zero = pivoted.zero_keyframes()
    np.testing.assert_array_equal(pivoted.controls(pivoted.offsets(zero, idx), idx)[1][0], plain.wrist_pos)
    turn = zero.copy()
    turn[:, 12] = 3.0  # 0.3 rad about z
    _, p_plain, r_plain = plain.controls(plain.offsets(turn, idx), idx)
    _, p_pivot, r_pivot = pivoted.controls(pivoted.offsets(turn, idx), idx)
    np.testing.assert_allclose(r_pivot, r_plain)  # the same orientation ...
    np.testing.assert_array_equal(p_plain[0], plain.wrist_pos)  # ... about the wrist, the wrist stays ...
    arm = p_pivot[0] - centre  # ... about the pivot, the wrist swings round it at the same distance
    np.testing.assert_allclose(np.linalg.norm(arm, axis=1), 0.08, atol=1e-12)
    # the recorded wrist quaternion is the identity, so the hand's rotation is the offset's
    np.testing.assert_allclose(arm, quat_rotate(r_pivot[0], np.tile([-0.08, 0.0, 0.0], (FRAMES, 1))), atol=1e-12)
    assert np.all(arm[:, 1] < -0.02)  # turned by ~0.3 rad about +z
    with pytest.raises(ValueError, match="pivot"):
        HandControlSpace("right", plain.q_ref, plain.wrist_pos, plain.wrist_quat, plain.q_limits, plain.basis,
                         interval=5, substeps=SUBSTEPS, pivot=centre[:3])


def _problem(threads: int = 1, ref_push: float = 0.03) -> tuple[SimWindowProblem, ParallelEvaluator]:
    layout, space, start = tiny_setup()
    ev = ParallelEvaluator(layout.model, threads)
    # Reference object motion = what a known control (the reference hand) produces in simulation.
    ref_layout, ref_space, _ = tiny_setup(ref_push)
    ref_problem = SimWindowProblem(ref_layout, {"right": ref_space}, _dummy_obj(), _dummy_hand(), resolve_weights({}),
                                   ev, start)
    control, _ = ref_problem.build_control({"right": ref_space.zero_keyframes()}, 0, FRAMES - 1)
    states, sensors = ev.rollout(start, control)
    rec = ref_problem._record(0, FRAMES - 1, states, sensors, {"right": np.zeros((1, FRAMES, 13))})
    a = ref_layout.object_sensor_adr
    pos = np.concatenate([sensors[0, :1, a : a + 3], rec.obj_pos[0]])
    quat = np.concatenate([sensors[0, :1, a + 3 : a + 7], rec.obj_quat[0]])
    obj = ObjectTargets(pos, quat, finite_difference_velocity(pos, quat, FPS))
    weights = resolve_weights({"hand_joints": 0.0, "fingertip_contact": 0.0, "hand_velocity": 0.0})
    return SimWindowProblem(layout, {"right": space}, obj, _dummy_hand(), weights, ev, start), ev


def _dummy_obj() -> ObjectTargets:
    return ObjectTargets(np.zeros((FRAMES, 3)), np.tile([1.0, 0, 0, 0], (FRAMES, 1)), np.zeros((FRAMES, 6)))


def _dummy_hand() -> dict[str, HandKeypointTargets]:
    return {"right": HandKeypointTargets(np.zeros((FRAMES, 3, 3)), np.ones(FRAMES, bool), (1, 2),
                                 np.zeros((FRAMES, 2), bool), np.zeros((FRAMES, 2, 3)))}


def test_rollout_matches_python_stepping_and_ignores_history() -> None:
    problem, ev = _problem(threads=2)
    with ev:
        kf = {"right": problem.spaces["right"].zero_keyframes()}
        cand = {"right": np.random.default_rng(1).normal(size=(4, 13))}
        control, _ = problem.build_control(kf, 0, 10, 2, cand)
        states, _ = ev.rollout(problem.initial, control)
        again, _ = ev.rollout(problem.initial, control[::-1])  # other order, other threads' history
        np.testing.assert_array_equal(states, again[::-1])
        python_states, _ = problem._step_recording(problem.initial, control[1])
        np.testing.assert_array_equal(states[1], python_states)
    single, ev1 = _problem(threads=1)
    with ev1:
        states1, _ = ev1.rollout(single.initial, control)
    np.testing.assert_array_equal(states, states1)


def test_windowed_cma_recovers_a_known_push() -> None:
    # The reference pushes the box 2 cm further than the controls do; the window loop must find wrist motion
    # that reproduces it (here only the 3 rotation coordinates matter, plus free translation when enabled).
    problem, ev = _problem(ref_push=0.05)
    problem.spaces["right"].free_translation = True
    with ev:
        kf0 = {"right": problem.spaces["right"].zero_keyframes()}
        before = _final_object_error(problem, ev, kf0)
        kf, logs = optimise_windows(problem, CmaSettings(popsize=8, max_generations=12, skip_loss=0.0, seed=3))
    final_err = _final_object_error(problem, ev, kf)
    assert len(logs) == problem.n_keyframes - 1  # keyframe 0 is the start state
    assert before > 0.015, before  # the unrefined controls miss by the 2 cm extra push
    assert final_err < 0.005, final_err


def _final_object_error(problem: SimWindowProblem, ev: ParallelEvaluator, kf: dict[str, np.ndarray]) -> float:
    ev2 = ParallelEvaluator(problem.layout.model, 1)
    control, offs = problem.build_control(kf, 0, FRAMES - 1)
    states, sensors = ev2.rollout(problem.initial, control)
    rec = problem._record(0, FRAMES - 1, states, sensors, offs)
    ev2.close()
    return float(np.linalg.norm(rec.obj_pos[0] - problem.obj.pos[1:], axis=-1).max())


def test_lookahead_frames_weigh_the_object_rotation_by_the_lookahead_factor() -> None:
    # Window j simulates up to keyframe j + lookahead; the frames past keyframe j + 1 are the lookahead, where the
    # rotation error counts by ``lookahead_rotation_weight``; a whole-sequence record (no window) weighs all alike.
    layout, space, start = tiny_setup()
    with ParallelEvaluator(layout.model, 1) as ev:
        problem = SimWindowProblem(layout, {"right": space}, _dummy_obj(), _dummy_hand(), resolve_weights({}), ev,
                                   start, lookahead=2, lookahead_rotation_weight=0.25)
        kf = {"right": space.zero_keyframes()}
        j = 2
        f0, f1 = problem.window(j)
        assert (f0, f1) == (0, 4 * space.interval)
        control, offs = problem.build_control(kf, f0, f1)
        states, sensors = ev.rollout(start, control)
        rec = problem._record(f0, f1, states, sensors, offs, j)
        assert rec.rotation_weight is not None
        frames = np.arange(f0 + 1, f1 + 1)
        np.testing.assert_array_equal(rec.rotation_weight, np.where(frames > 3 * space.interval, 0.25, 1.0))
        assert problem._record(f0, f1, states, sensors, offs).rotation_weight is None


def test_probe_is_the_one_candidate_evaluation_and_sees_the_push() -> None:
    # The probe records only the frame steps and checks contacts with one array lookup per step; its loss must be
    # the batched rollout's for the same keyframes, and it must see the paddle touch the box it pushes.
    problem, ev = _problem(ref_push=0.05)
    with ev:
        kf = {"right": problem.spaces["right"].zero_keyframes()}
        for j in range(1, problem.n_keyframes):
            loss, touched = problem.probe(j, problem.initial, kf)
            batched = problem.evaluate(j, problem.initial, kf, {"right": kf["right"][j][None]})
            assert loss["right"] == batched["right"][0]
            assert touched
    layout, away, start = tiny_setup(push=-0.03)  # the paddle backs off: it never reaches the box
    with ParallelEvaluator(layout.model, 1) as ev_away:
        backing = SimWindowProblem(layout, {"right": away}, _dummy_obj(), _dummy_hand(), resolve_weights({}),
                                   ev_away, start)
        kf_away = {"right": away.zero_keyframes()}
        assert not any(backing.probe(j, start, kf_away)[1] for j in range(1, backing.n_keyframes))
