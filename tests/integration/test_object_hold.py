"""The object's hold before the hand arrives (``SimConfig.hold_until_m``): a box recorded 5 cm above a bare
table (on something the scene does not have) stays where it was recorded while it rests untouched in the
recording, falls once released, and every rollout path (Python stepping, ``mujoco.rollout`` windows, the refined
replay that ``verify`` repeats) switches the hold off on the same physics step."""

from __future__ import annotations

import numpy as np
import pytest

from common.geometry import quat_rotate
from common.job_options import JobOptions
from common.sequence import Sequence
from tests.integration.test_scene_physics import _box_sequence, _replay
from worker.refine.evaluator import ParallelEvaluator, control_columns
from worker.refine.prepare import prepare, settled_start
from worker.refine.replay import window_problem
from worker.refine.result import verify_result
from worker.refine.run import refine_sequence
from worker.simulation.config import OLDER_SIM_DEFAULTS
from worker.simulation.scene import SimConfig

FRAMES = 14
#: No table under the box but the level one at z = 0: no shelf, no tilted candidates.
BARE_TABLE = SimConfig(table_shelf=False, table_max_tilt_deg=0.0)


def _floating_box(moves_at: int | None = None) -> Sequence:
    """A 6 cm box recorded with its centre 8 cm up (bottom 5 cm above the table), hands 40 cm above it; from frame
    ``moves_at`` on the recorded box is 2 cm lower (it has moved: the recording no longer shows it resting)."""
    seq = _box_sequence(frames=FRAMES, z=0.08)
    if moves_at is not None:
        seq.object_pose[moves_at:, 2] -= 0.02
    return seq.validate()


def _heights(seq: Sequence, config: SimConfig) -> tuple[int, np.ndarray]:
    _, scene, rec = _replay(seq, config)
    return scene.object_release_frame, rec.object_pose[:, 2]


@pytest.mark.parametrize("hold", [True, False])
def test_a_box_resting_on_something_unsimulated_stays_put_while_held(hold: bool) -> None:
    """Never approached, never moving in the recording: held for the whole sequence; without the hold it falls."""
    release, z = _heights(_floating_box(), SimConfig(table_shelf=False, table_max_tilt_deg=0.0,
                                                     hold_until_m=0.05 if hold else 0.0))
    if hold:
        assert release == FRAMES
        assert np.abs(z - 0.08).max() < 1e-3
    else:
        assert release == 0
        assert z[-1] < 0.07


def test_the_hold_ends_when_the_recorded_object_starts_to_move() -> None:
    release, z = _heights(_floating_box(moves_at=6), BARE_TABLE)
    assert release == 6
    assert np.abs(z[:7] - 0.08).max() < 1e-3  # held through frame 6's state (the steps before it)
    assert z[7] < 0.078 and z[-1] == pytest.approx(0.03, abs=1e-3)  # then it falls onto the table


def test_every_rollout_path_switches_the_hold_off_on_the_same_step() -> None:
    """A window rollout in C (``mujoco.rollout``, the hold switched through the controls) from before the release
    to after it equals Python stepping of the same controls, and both leave the box falling."""
    seq = _floating_box(moves_at=6)
    prep = prepare(seq, JobOptions(popsize=4, max_generations=1), BARE_TABLE)
    assert prep.layout.release_frame == 6 and prep.layout.hold_eq >= 0
    with ParallelEvaluator(prep.scene.model, 2) as ev:
        start, _ = settled_start(prep, ev)
        problem = window_problem(prep, ev, start, {})
        keyframes = {side: sp.zero_keyframes() for side, sp in prep.spaces.items()}
        control, _ = problem.build_control(keyframes, 0, FRAMES - 1)
        switches = control[0, :, control_columns(prep.scene.model).eq_active][:, prep.layout.hold_eq]
        assert switches[: 6 * prep.layout.substeps].all() and not switches[6 * prep.layout.substeps :].any()
        states, _ = ev.rollout(start, control)
        python_states, _ = problem._step_recording(start, control[0])
    np.testing.assert_array_equal(states[0], python_states)
    z_adr = 1 + prep.scene.object_qpos_adr + 2  # FULLPHYSICS starts with the time
    z = states[0, :, z_adr]
    spf = prep.layout.substeps
    assert abs(z[6 * spf - 1] - 0.08) < 1e-3 and z[-1] < 0.075


def test_a_refinement_with_the_hold_verifies_and_older_results_replay_without_it() -> None:
    seq = _floating_box(moves_at=6)
    out = refine_sequence(seq, JobOptions(popsize=4, max_generations=1, restarts=0), threads=1, config=BARE_TABLE)
    assert out.summary["config"]["sim"]["hold_until_m"] == SimConfig().hold_until_m > 0
    assert np.abs(out.arrays["object_pose_sim"][:7, 2] - 0.08).max() < 1e-3
    # The bare table is not the product's default (``--allow-config``); the hold is.
    assert verify_result(out.to_npz_bytes(), allow_config=True)["max_pos_diff_m"] == 0.0
    assert OLDER_SIM_DEFAULTS["hold_until_m"] == 0.0  # results that do not record it had no hold


def _box_on_its_edge(approach_at: int, moves_at: int) -> Sequence:
    """A 6 cm box recorded standing on one edge, 35 degrees over (it leaned on something the scene does not have:
    no table holds it so); the hand's lowest keypoint comes down to 15 mm above the box's highest corner by frame
    ``approach_at``, and the recorded box moves 2 cm sideways from frame ``moves_at``."""
    tilt = np.radians(35.0)
    seq = _box_sequence(frames=FRAMES, tilt_deg=35.0, z=0.03 * (np.cos(tilt) + np.sin(tilt)) + 0.001)
    corners = np.array([[x, y, z] for x in (-0.03, 0.03) for y in (-0.03, 0.03) for z in (-0.03, 0.03)])
    top = quat_rotate(np.broadcast_to(seq.object_pose[0, 3:], (8, 4)), corners)[:, 2].argmax()
    above = quat_rotate(seq.object_pose[0, 3:], corners[top]) + seq.object_pose[0, :3] + [0.0, 0.0, 0.015]
    kp = seq.hands[0].keypoints
    assert kp is not None
    lowest = kp[np.arange(FRAMES), kp[:, :, 2].argmin(axis=1)]  # (T, 3)
    share = np.clip(np.arange(FRAMES) / approach_at, 0.0, 1.0)[:, None]
    kp += (share * (above - lowest))[:, None, :]
    seq.object_pose[moves_at:, 0] += 0.02
    return seq.validate()


@pytest.mark.parametrize("unsupported_drift", [SimConfig().unsupported_drift, 0.0])
def test_an_object_no_table_can_hold_is_held_until_the_recording_moves_it(unsupported_drift: float) -> None:
    """Released as the hand comes near (the rule for an object the scene supports), a box standing on its edge
    falls before any grasp can form; since no table the fit tries holds it, it is held until just before the
    recorded box moves instead."""
    seq = _box_on_its_edge(approach_at=4, moves_at=9)
    _, scene, rec = _replay(seq, SimConfig(unsupported_drift=unsupported_drift))
    release, z = scene.object_release_frame, rec.object_pose[:, 2]
    assert SimConfig().unsupported_drift > 0 and scene.table_drift > 20  # it fell flat in the fit
    assert scene.hold_summary() == {"release_frame": release, "until_recording_moves": unsupported_drift > 0}
    if unsupported_drift > 0:
        lead = round(SimConfig().unsupported_lead_s * seq.fps)
        assert lead == 2 and release == 9 - lead  # released just before the recording moves it
        assert np.ptp(z[: release + 1]) < 1e-4  # where it starts (snapped onto the table) until then
    else:
        assert release == 4
        assert z[9] < z[0] - 0.01  # fallen onto a face by then
