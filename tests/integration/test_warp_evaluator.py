"""``WarpEvaluator`` (issue #19 item 5) against ``ParallelEvaluator``, on Warp's CPU device.

Skipped unless the optional ``.[gpu]`` packages are installed (CI does not install them). Warp's CPU device runs
the same MuJoCo Warp kernels as a GPU, in float32, so these pin the layout, the convention and the overflow
handling without a GPU; the first run compiles the kernels (about a minute), later runs load them from Warp's
cache.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mujoco_warp")

from common.job_options import JobOptions
from worker.example import short_example_sequence
from worker.refine.evaluator import ParallelEvaluator
from worker.refine.losses import resolve_weights
from worker.refine.prepare import prepare, settled_start
from worker.refine.replay import window_problem
from worker.refine.result import verify_result
from worker.refine.run import refine_sequence
from worker.refine.warp_evaluator import WarpEvaluator

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def setup():
    prep = prepare(short_example_sequence(), JobOptions())
    cpu = ParallelEvaluator(prep.scene.model, 1)
    start, _ = settled_start(prep, cpu)
    problem = window_problem(prep, cpu, start, resolve_weights(None))
    keyframes = {s: np.zeros((problem.n_keyframes, problem.dim(s))) for s in problem.sides}
    yield prep, cpu, start, problem, keyframes
    cpu.close()


def _population(problem, keyframes, j: int, n: int):
    rng = np.random.default_rng(j)
    cands = {s: 0.5 * rng.standard_normal((n, problem.dim(s))) for s in problem.sides}
    f0, f1 = problem.window(j)
    return problem.build_control(keyframes, f0, f1, j, cands)[0]


def test_rollout_keeps_the_cpu_layout_and_convention(setup) -> None:
    prep, cpu, start, problem, keyframes = setup
    control = _population(problem, keyframes, 1, 3)
    states, sensors = cpu.rollout(start, control)
    with WarpEvaluator(prep.scene.model, device="cpu") as gpu:
        g_states, g_sensors = gpu.rollout(start, control)
        assert gpu.stats.steps == control.shape[0] * control.shape[1] and gpu.stats.rollouts == 3
    assert g_states.shape == states.shape and g_sensors.shape == sensors.shape
    assert g_states.dtype == np.float64
    # time, then qpos: float32 agreement (the hand approaches; no contact yet in window 1)
    np.testing.assert_allclose(g_states[..., 0], states[..., 0], atol=1e-5)
    nq = prep.scene.model.nq
    np.testing.assert_allclose(g_states[..., 1 : 1 + nq], states[..., 1 : 1 + nq], atol=1e-3)
    # Sensors of step s are those at its start: step 0's keypoints are the start state's on both.
    kp = problem.layout.hands[problem.sides[0]].keypoint_sensor_adrs
    np.testing.assert_allclose(g_sensors[:, 0, kp], sensors[:, 0, kp], atol=1e-5)
    np.testing.assert_allclose(g_sensors[:, :, kp], sensors[:, :, kp], atol=2e-3)
    # The three candidates differ, so each world ran its own controls.
    assert np.abs(g_states[0, -1] - g_states[1, -1]).max() > 1e-4


def test_contact_overflow_grows_the_buffers_and_repeats_the_rollout(setup) -> None:
    prep, cpu, start, problem, keyframes = setup
    # The full zero-offset pass: the hand closes on the box and lifts it (many contacts).
    f_last = problem.num_frames - 1
    control = np.repeat(problem.build_control(keyframes, 0, f_last)[0], 2, axis=0)
    with WarpEvaluator(prep.scene.model, device="cpu", nconmax=1, njmax=8) as tight, \
            WarpEvaluator(prep.scene.model, device="cpu", nconmax=64, njmax=512) as roomy:
        t_states, _ = tight.rollout(start, control)
        r_states, _ = roomy.rollout(start, control)
        assert tight.regrowths >= 1 and roomy.regrowths == 0
    cpu_states, _ = cpu.rollout(start, control)
    obj = prep.scene.object_qpos_adr
    lift = cpu_states[0, :, 1 + obj + 2].max() - cpu_states[0, 0, 1 + obj + 2]
    assert lift > 0.005, "the zero-offset pass of the example lifts the box (contacts happen)"
    # With room enough, the tight evaluator's repeated rollout is the roomy one's; both follow the CPU's lift.
    np.testing.assert_allclose(t_states, r_states, atol=1e-4)
    g_lift = r_states[0, :, 1 + obj + 2].max() - r_states[0, 0, 1 + obj + 2]
    assert abs(g_lift - lift) < 0.002


def test_refinement_ranks_on_warp_and_derives_the_result_on_the_cpu() -> None:
    seq = short_example_sequence()
    options = JobOptions(popsize=4, max_generations=1, restarts=0)
    import mujoco

    with WarpEvaluator(mujoco.MjModel.from_xml_string("<mujoco/>"), device="cpu") as ev:
        outcome = refine_sequence(seq, options, evaluator=ev)
        assert ev.gpu_steps > 0 and ev.gpu_steps == ev.stats.steps - ev.stats.python_steps
    # The result is the CPU replay of the chosen keyframes, which ``verify`` repeats in MuJoCo's C engine: the
    # object's motion in it comes from CPU simulation, bit for bit, whatever ranked the candidates.
    assert verify_result(outcome.to_npz_bytes())["max_pos_diff_m"] == 0.0
    assert outcome.summary["timings"]["rollout_steps"] > 0
