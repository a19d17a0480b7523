"""Stepwise verification (issue #54): a result stores every frame's integration state of both replays; ``verify``
checks each frame against the one before it, so it stays tight on any host, and a stored state that teleports the
object, adds a force or moves the hand off its controls fails naming the field and the frame."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from common.job_options import JobOptions
from common.result_format import STEPWISE_KEYS, read_arrays, read_summary, write_result_npz
from tests.support.verify_failures import fails_naming
from worker.refine.prepare import Prepared
from worker.refine.result import prepare_from_result
from worker.refine.run import refine_sequence
from worker.verification import check_result
from worker.verification.stepwise import StateLayout

ROOT = Path(__file__).resolve().parents[2]
#: NumPy's AVX-512 kernels off and OpenBLAS's Haswell kernels: what an AVX2 host runs.
OTHER_KERNELS = {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR AVX512_SKX", "OPENBLAS_CORETYPE": "Haswell"}

Result = tuple[dict[str, np.ndarray], dict[str, Any]]


@pytest.fixture(scope="module")
def honest() -> Result:
    """A refined grasp-and-lift (the built-in example) as stored arrays + summary."""
    from worker.example import short_example_sequence

    outcome = refine_sequence(short_example_sequence(), JobOptions(popsize=4, max_generations=1, restarts=0))
    blob = outcome.to_npz_bytes(wall_clock=False)
    return read_arrays(blob), read_summary(blob)


@pytest.fixture(scope="module")
def prep(honest: Result) -> Prepared:
    arrays, summary = honest
    return prepare_from_result(write_result_npz(arrays, summary, wall_clock=False))[0]


def _blob(arrays: dict[str, np.ndarray], summary: dict[str, Any]) -> bytes:
    return write_result_npz(arrays, summary, wall_clock=False)


def test_a_result_stores_both_replays_states_and_verifies_stepwise(honest: Result, prep: Prepared) -> None:
    arrays, summary = honest
    layout = StateLayout(prep.layout.model)
    for key in ("state_sim", "raw_state_sim"):
        assert arrays[key].shape == (len(arrays["object_pose_sim"]), layout.size) and arrays[key].dtype == np.float64
    # A frame's state holds the object where the trajectory has it.
    a = prep.scene.object_qpos_adr
    qpos = layout.part(arrays["state_sim"], "qpos")
    np.testing.assert_array_equal(qpos[:, a : a + 7], arrays["object_pose_sim"])
    report = check_result(_blob(arrays, summary))
    assert report.failures == [] and report.method == "stepwise" and report.exact
    assert set(report.stepwise) == {"refined", "raw"} and all(r.exact for r in report.stepwise.values())
    assert {"state_sim", "raw_state_sim"} <= set(report.checked)
    out = report.to_dict()
    assert out["verified"] and out["method"] == "stepwise" and out["stepwise"]["refined"]["frames"] == len(qpos)


def test_the_state_layout_follows_mujoco(prep: Prepared) -> None:
    model = prep.layout.model
    layout = StateLayout(model)
    data = mujoco.MjData(model)
    data.qvel[:] = 7.0
    data.xfrc_applied[:] = 3.0
    data.ctrl[:] = 5.0
    state = np.zeros(layout.size)
    mujoco.mj_getState(model, data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
    assert (layout.part(state, "qvel") == 7.0).all() and (layout.part(state, "xfrc_applied") == 3.0).all()
    assert (layout.part(state, "ctrl") == 5.0).all() and (layout.part(state, "qacc_warmstart") == 0.0).all()


@pytest.mark.slow
def test_an_honest_result_verifies_stepwise_with_other_kernels_forced(honest: Result, tmp_path: Path) -> None:
    """Another x86_64 host, emulated in a subprocess: the stepwise check passes (bit-identical where this machine
    has no AVX-512, within micrometres elsewhere) and vouches for the same content."""
    arrays, summary = honest
    path = tmp_path / "r.npz"
    path.write_bytes(_blob(arrays, summary))
    env = {**os.environ, **OTHER_KERNELS, "PYTHONPATH": str(ROOT)}
    run = subprocess.run([sys.executable, "-m", "common.cli", "verify", str(path)], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "stepwise state_sim: " in run.stdout and "stepwise raw_state_sim: " in run.stdout
    assert "verify: OK" in run.stdout
    assert f"checked sha256 {check_result(path.read_bytes()).digest}" in run.stdout


def test_a_teleported_object_fails_at_its_frame(honest: Result, prep: Prepared) -> None:
    """The object moved 5 cm at frame 12 in the stored state and the trajectory alike (consistent arrays)."""
    arrays, summary = honest
    layout, a = StateLayout(prep.layout.model), prep.scene.object_qpos_adr
    states, pose = arrays["state_sim"].copy(), arrays["object_pose_sim"].copy()
    states[12, layout.slices["qpos"].start + a] += 0.05
    pose[12, 0] += 0.05
    fails_naming(_blob({**arrays, "state_sim": states, "object_pose_sim": pose}, summary),
                  "state_sim.qpos", "at frame 12", "x position")


def test_a_trajectory_shifted_3_mm_fails_at_its_first_frame(honest: Result, prep: Prepared) -> None:
    """Within the old cross-host tolerance (5 mm + 10 %): the trajectory and its states moved 3 mm over frames
    10-15, every figure recomputed from the moved trajectory would agree; the stepwise check names frame 10."""
    arrays, summary = honest
    layout, a = StateLayout(prep.layout.model), prep.scene.object_qpos_adr
    states, pose = arrays["state_sim"].copy(), arrays["object_pose_sim"].copy()
    states[10:16, layout.slices["qpos"].start + a + 2] += 0.003
    pose[10:16, 2] += 0.003
    text = fails_naming(_blob({**arrays, "state_sim": states, "object_pose_sim": pose}, summary),
                         "state_sim.qpos", "at frame 10", "z position")
    assert "0.003" in text


def test_an_added_force_fails(honest: Result, prep: Prepared) -> None:
    arrays, summary = honest
    layout = StateLayout(prep.layout.model)
    states = arrays["state_sim"].copy()
    body = prep.scene.object_body_id
    states[8:, layout.slices["xfrc_applied"].start + 6 * body + 2] = 0.5  # 0.5 N upwards on the object
    fails_naming(_blob({**arrays, "state_sim": states}, summary), "state_sim.xfrc_applied", "at frame 8",
                  "force", "only through contact")
    qfrc = arrays["raw_state_sim"].copy()
    qfrc[3, layout.slices["qfrc_applied"].start] = 1.0
    fails_naming(_blob({**arrays, "raw_state_sim": qfrc}, summary), "raw_state_sim.qfrc_applied", "at frame 3")


def test_a_force_simulated_then_hidden_fails_where_it_acted(honest: Result, prep: Prepared) -> None:
    """The forger's better try: the refined replay simulated with a push on the object during frames 10-11, every
    array stored from that simulation, the force zeroed in the stored states."""
    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.prepare import settled_start
    from worker.refine.replay import replay

    arrays, summary = honest
    spf, body = prep.layout.substeps, prep.scene.object_body_id

    def push(i: int, d: mujoco.MjData) -> None:
        d.xfrc_applied[body, 2] = 2.0 if 10 * spf - 1 <= i < 12 * spf - 1 else 0.0

    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = settled_start(prep, ev)
        rec = replay(prep, ev, start, {"right": arrays["right_keyframes"]}, on_step=push, record_states=True)
    assert rec.states is not None
    layout = StateLayout(prep.layout.model)
    states = rec.states.copy()
    states[:, layout.slices["xfrc_applied"]] = 0.0
    assert not np.array_equal(rec.object_pose, arrays["object_pose_sim"])
    fails_naming(_blob({**arrays, "state_sim": states, "object_pose_sim": rec.object_pose}, summary),
                  "state_sim.q", "at frame 11")


def test_nudges_each_within_the_per_frame_tolerance_fail_by_what_they_add_up_to(honest: Result,
                                                                                 prep: Prepared) -> None:
    """The forger's patient try: every frame from frame 4 on, the object's upward velocity half the per-frame
    tolerance above where the frame before leads. No frame is beyond its bound; the running sum of the deviations
    (the velocity the nudges add up to) is, from the frame where it passes its own bound."""
    from worker.verification.stepwise import STATE_TOLERANCES, StepwiseReport, _compare

    arrays, _ = honest
    layout = StateLayout(prep.layout.model)
    reached = arrays["state_sim"].copy()
    stored = reached.copy()
    step = STATE_TOLERANCES.qvel / 2
    stored[4:, layout.slices["qvel"].start + prep.scene.object_dof_adr + 2] += step
    report = StepwiseReport("state_sim")
    _compare(report, layout, stored, reached, "state_sim", STATE_TOLERANCES)
    assert report.largest["qvel"].value < STATE_TOLERANCES.qvel
    crossing = 4 + int(STATE_TOLERANCES.running_qvel / step)  # the first frame whose sum passes the bound
    (failure,) = report.failures
    assert failure.startswith("state_sim.qvel: the per-frame deviations add up to ") and \
        f"by frame {crossing} (object_root z position" in failure, failure


def test_a_hand_moved_off_its_controls_fails(honest: Result, prep: Prepared) -> None:
    arrays, summary = honest
    model = prep.layout.model
    layout = StateLayout(model)
    hand = prep.scene.hands["right"]
    joint = int(hand.qpos_adr[5])
    states = arrays["state_sim"].copy()
    states[15, layout.slices["qpos"].start + joint] += 0.05  # a finger bent 3 degrees further
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, int(np.flatnonzero(model.jnt_qposadr == joint)[0]))
    fails_naming(_blob({**arrays, "state_sim": states}, summary), "state_sim.qpos", "at frame 15", str(name))
    ctrl = arrays["state_sim"].copy()
    ctrl[15, layout.slices["ctrl"].start + 3] += 0.1  # a servo target the keyframes do not give
    fails_naming(_blob({**arrays, "state_sim": ctrl}, summary), "state_sim.ctrl", "at frame 15",
                  "the stored controls")
    wrist = arrays["state_sim"].copy()
    wrist[9:, layout.slices["mocap_pos"].start + 3 * hand.mocap_id] += 0.002  # the wrist's target moved 2 mm
    fails_naming(_blob({**arrays, "state_sim": wrist}, summary), "state_sim.mocap_pos", "at frame 9")


def test_states_of_another_shape_or_not_numbers_fail(honest: Result, prep: Prepared) -> None:
    arrays, summary = honest
    fails_naming(_blob({**arrays, "raw_state_sim": arrays["raw_state_sim"][:, :-1]}, summary),
                  "raw_state_sim: shape")
    states = arrays["state_sim"].copy()
    states[7, StateLayout(prep.layout.model).slices["qvel"].start] = np.nan
    fails_naming(_blob({**arrays, "state_sim": states}, summary), "state_sim.qvel: not a finite number at frame 7")


def test_an_older_result_without_states_verifies_the_old_way_with_a_note(honest: Result) -> None:
    arrays, summary = honest
    old = {k: v for k, v in arrays.items() if k not in STEPWISE_KEYS}
    report = check_result(_blob(old, summary))
    assert report.failures == [] and report.method == "rollout" and report.exact and not report.stepwise
    assert any(n.startswith("no stored states (older result)") for n in report.config_notes), report.config_notes
    moved = old["object_pose_sim"].copy()
    moved[20, 0] += 0.002
    fails_naming(_blob({**old, "object_pose_sim": moved}, summary), "frame 20")


def test_recording_the_states_leaves_the_replay_as_it_was(honest: Result, prep: Prepared) -> None:
    """Storing states must not change a refinement's numbers: the same replay with and without them, bit for bit."""
    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.prepare import settled_start
    from worker.refine.replay import ReplayJob, replay_all

    arrays, _ = honest
    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = settled_start(prep, ev)
    keyframes = {"right": arrays["right_keyframes"]}
    (plain, recorded), _ = replay_all(prep, start, [ReplayJob(keyframes), ReplayJob(keyframes, record_states=True)])
    assert plain.states is None and recorded.states is not None
    np.testing.assert_array_equal(recorded.states, arrays["state_sim"])
    for name in ("object_pose", "object_vel", "articulation"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(recorded, name))
    np.testing.assert_array_equal(plain.keypoints["right"], recorded.keypoints["right"])
    for key, column in plain.contacts.items():
        np.testing.assert_array_equal(column, recorded.contacts[key])


def test_a_result_stores_every_steps_inputs_and_steps_under_them(honest: Result, prep: Prepared) -> None:
    """The inputs of every physics step are stored beside the states; the stepwise check steps under them after
    checking them against the keyframes', so last-bit differences in the inputs made on another host do not
    enter the physics."""
    from worker.refine.evaluator import control_size

    arrays, summary = honest
    frames, spf = len(arrays["object_pose_sim"]), prep.layout.substeps
    for key in ("control_sim", "raw_control_sim"):
        assert arrays[key].shape == ((frames - 1) * spf + 1, control_size(prep.layout.model))
    # The state of frame f holds the inputs of the step that ended it.
    layout = StateLayout(prep.layout.model)
    np.testing.assert_array_equal(layout.part(arrays["state_sim"][1:], "ctrl"),
                                  arrays["control_sim"][spf - 1 : -1 : spf, : prep.layout.model.nu])
    report = check_result(_blob(arrays, summary))
    assert report.failures == [] and report.exact
    assert {"refined", "raw"} == set(report.stepwise)
    assert all(r.controls is not None and r.controls.value == 0.0 for r in report.stepwise.values())
    # Inputs 1e-12 off the keyframes' (another host's last bits): accepted, stepped under as stored.
    nudged = arrays["control_sim"].copy()
    nudged[40:, : prep.layout.model.nu] += 1e-12
    report = check_result(_blob({**arrays, "control_sim": nudged}, summary))
    assert report.stepwise["refined"].controls is not None and report.stepwise["refined"].controls.value > 0
    assert not any("control_sim" in f for f in report.failures), report.failures


def test_stored_inputs_off_the_keyframes_fail_naming_the_input_and_frame(honest: Result, prep: Prepared) -> None:
    arrays, summary = honest
    model, spf = prep.layout.model, prep.layout.substeps
    hand = prep.scene.hands["right"]
    actuator = int(hand.actuator_ids[2])
    controls = arrays["control_sim"].copy()
    controls[13 * spf + 3 :, actuator] += 0.05  # a servo target the keyframes do not give, from frame 13 on
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, actuator)
    fails_naming(_blob({**arrays, "control_sim": controls}, summary), "control_sim: 0.05 from the keyframes'",
                  "at frame 13", f"ctrl {name}")
    wrist = arrays["raw_control_sim"].copy()
    wrist[5 * spf :, model.nu + model.neq + 3 * hand.mocap_id + 2] += 0.003  # the raw wrist's target 3 mm up
    fails_naming(_blob({**arrays, "raw_control_sim": wrist}, summary), "raw_control_sim", "at frame 5",
                  "mocap_pos")
    fails_naming(_blob({**arrays, "control_sim": arrays["control_sim"][:-1]}, summary), "control_sim: shape")


def test_a_result_with_states_but_no_stored_inputs_steps_under_the_keyframes_with_a_note(honest: Result) -> None:
    arrays, summary = honest
    older = {k: v for k, v in arrays.items() if k not in ("control_sim", "raw_control_sim")}
    report = check_result(_blob(older, summary))
    assert report.failures == [] and report.method == "stepwise" and report.exact
    assert all(r.controls is None for r in report.stepwise.values())
    assert any(n.startswith("no stored inputs") for n in report.config_notes), report.config_notes


@pytest.mark.slow
def test_with_other_kernels_forced_every_frame_is_reached_bit_for_bit(honest: Result, tmp_path: Path) -> None:
    """Under the stored inputs, the kernels NumPy and OpenBLAS pick do not enter the physics: every frame is
    reached exactly, frame 0 too (settled from the stored pre-settle state)."""
    arrays, summary = honest
    path = tmp_path / "r.npz"
    path.write_bytes(_blob(arrays, summary))
    script = ("import json, sys; from pathlib import Path; from worker.verification import check_result; "
              "r = check_result(Path(sys.argv[1]).read_bytes()); "
              "print(json.dumps({'failures': r.failures, 'largest': {k: max([d.value for d in s.largest.values()] "
              "+ [d.value for d in s.start.values()] + [0.0]) for k, s in r.stepwise.items()}}))")
    for kernels in (OTHER_KERNELS, {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR AVX512_SKX",
                                    "OPENBLAS_CORETYPE": "Nehalem"}):
        env = {**os.environ, **kernels, "PYTHONPATH": str(ROOT)}
        run = subprocess.run([sys.executable, "-c", script, str(path)], env=env, cwd=ROOT, capture_output=True,
                             text=True, timeout=600)
        assert run.returncode == 0, run.stderr
        out = json.loads(run.stdout.strip().splitlines()[-1])
        assert out["failures"] == [] and out["largest"] == {"refined": 0.0, "raw": 0.0}, (kernels, out)


def test_frame_0_settles_from_the_stored_pre_settle_state(honest: Result, prep: Prepared) -> None:
    """The settling to frame 0 is steps like any frame's: the result stores the state it starts from, verify
    checks that against the start placed here (hands at their frame-0 targets, the object at its recorded pose)
    and compares frame 0 with the settling from it as tightly as any other frame."""
    from worker.refine.prepare import presettle_state

    arrays, summary = honest
    np.testing.assert_array_equal(arrays["presettle_state_sim"], presettle_state(prep))
    report = check_result(_blob(arrays, summary))
    assert report.failures == [] and all(r.presettle is not None and r.presettle.value == 0.0
                                         for r in report.stepwise.values())
    layout, a = StateLayout(prep.layout.model), prep.scene.object_qpos_adr
    moved = arrays["presettle_state_sim"].copy()
    moved[layout.slices["qpos"].start + a + 1] += 0.002  # the object placed 2 mm off its recorded pose
    fails_naming(_blob({**arrays, "presettle_state_sim": moved}, summary), "presettle_state_sim.qpos: 0.002",
                 "object_root y position", "the recorded start")
    fails_naming(_blob({**arrays, "presettle_state_sim": moved[:-1]}, summary), "presettle_state_sim: shape")
    older = {k: v for k, v in arrays.items() if k != "presettle_state_sim"}
    report = check_result(_blob(older, summary))
    assert report.failures == [] and any(n.startswith("no stored pre-settle state") for n in report.config_notes)
