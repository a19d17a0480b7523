"""The from-scratch replay of a sequence's keyframes (frame 0 to the end, every frame recorded, contacts too)
and the window problem it and the optimiser share.

Below both ``run`` (which replays the raw and the refined controls) and ``result`` (whose ``verify_result``
repeats that replay), so neither imports the other.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import mujoco
import numpy as np

from common.geometry import FloatArray
from worker.refine.evaluator import ParallelEvaluator, SimState, StepHook
from worker.refine.losses import resolve_weights
from worker.refine.prepare import Prepared
from worker.refine.problem import SimWindowProblem
from worker.simulation.contacts import ContactRecorder, empty_contact_columns
from worker.simulation.metrics import ContactFrames

#: What a result stores of every frame (``ReplayRecord.states``): MuJoCo's integration state, everything
#: ``mj_step`` reads (time, qpos, qvel, act, the solver warmstart, ctrl, applied forces, equality switches,
#: mocap poses, userdata, plugin state), so loading it and stepping reproduces the next frame bit for bit.
INTEGRATION_STATE = int(mujoco.mjtState.mjSTATE_INTEGRATION)

#: Keyframe intervals simulated past the optimised keyframe: 1 is the (k1..k4) window of DESIGN §1.6; 2 lets
#: the optimiser see whether a grasp holds one interval longer (on DexYCB dev it turned a dropped lift into a
#: success and lowered E_t elsewhere, for 28% more simulated steps; see bench/results/refine_dev.md).
LOOKAHEAD = 2
#: The factor on the object's rotation error over those lookahead frames in a refinement's first attempt (its
#: position, velocity and excursion terms count in full): 0. There the candidate's wrist turn is held as it is at
#: keyframe j + 1, which the next windows will change as the object turns, so charging every degree it leaves
#: there pulls keyframe j towards a compromise with frames it does not shape; whether the grasp holds the object
#: up is what the lookahead is for. On all 120 dev120 sequences it made E_t better on 79 and E_r on 74, but a few
#: grasps turned out or dropped (``bench/results/dev120_experiments.md``, fourth session), which is why the next
#: attempt charges the lookahead in full (``worker.refine.run.attempt_plan``).
LOOKAHEAD_ROTATION_WEIGHT = 0.0

@dataclass
class ReplayRecord:
    """A from-scratch replay: per-frame arrays (F frames) and contact columns."""

    object_pose: FloatArray  # (F, 7)
    object_vel: FloatArray  # (F, 6) world linear, angular
    keypoints: dict[str, FloatArray]  # side -> (F, 21, 3)
    contacts: dict[str, np.ndarray]
    steps: int
    #: Per-frame penetration / hand / table contact flags (``worker.simulation.metrics``); None without contacts.
    contact_frames: ContactFrames | None = None
    #: side -> (F, H) actuated joint positions, and the largest |actuator force| over each frame's physics steps
    #: (frame 0: its own state); robot hands only (``worker.robot.metrics``).
    joints: dict[str, FloatArray] = field(default_factory=dict)
    joint_force: dict[str, FloatArray] = field(default_factory=dict)
    #: side -> (F, H) the servo targets reached at each frame (robot hands only).
    command: dict[str, FloatArray] = field(default_factory=dict)
    #: (F, J) an articulated object's joint values; None for a rigid one.
    articulation: FloatArray | None = None
    #: (F, mj_stateSize(INTEGRATION)) the full integration state at every frame (``record_states``): frame f's is
    #: the state right before physics step f * substeps, inputs and solver warmstart included.
    states: FloatArray | None = None
    #: (steps, ncontrol) the inputs set before every physics step (``record_states``; ``CONTROL_SPEC`` columns):
    #: stored with the states so a stepwise check steps under the very bits the replay stepped under.
    controls: FloatArray | None = None


def replay_control(prep: Prepared, evaluator: ParallelEvaluator, start: SimState,
                   keyframes: dict[str, FloatArray]) -> FloatArray:
    """The (steps, ncontrol) inputs a replay of ``keyframes`` sets before each physics step, frame 0 -> F-1."""
    problem = window_problem(prep, evaluator, start, {})
    control, _ = problem.build_control(keyframes, 0, prep.num_frames - 1)
    return np.asarray(control[0])


def replay(prep: Prepared, evaluator: ParallelEvaluator, start: SimState, keyframes: dict[str, FloatArray],
           record_contacts: bool = True, on_step: StepHook | None = None, record_states: bool = False,
           control: FloatArray | None = None) -> ReplayRecord:
    """Simulate frame 0 -> F-1 with the given keyframes, recording every frame (and contacts, and with
    ``record_states`` the integration state of every frame and the inputs of every step: ``ReplayRecord.states``,
    ``.controls``).

    ``control`` steps under given inputs instead of those ``replay_control`` makes of the keyframes (a stepwise
    check under a result's stored inputs). ``on_step(i, data)`` also runs after physics step i, after the frame's
    records (the visual tools record the full state per frame; ``worker.verification.stepwise`` loads the stored
    next frame's state there)."""
    layout = prep.layout
    s = layout.substeps
    inputs = replay_control(prep, evaluator, start, keyframes) if control is None else np.asarray(control)
    n_frames = prep.num_frames
    sensors = np.empty((n_frames, layout.model.nsensordata))
    recorder = ContactRecorder(prep.scene) if record_contacts else None
    robots = {side: h for side, h in prep.scene.hands.items() if prep.hand_targets[side].joint_targets is not None}
    joints = {side: np.zeros((n_frames, len(h.qpos_adr))) for side, h in robots.items()}
    force = {side: np.zeros((n_frames, len(h.actuator_ids))) for side, h in robots.items()}
    states = frame_states(prep, start, n_frames) if record_states else None

    def hook(i: int, d: mujoco.MjData) -> None:
        if i % s == 0:  # contacts and sensors of this step were computed at the frame's state
            sensors[i // s] = d.sensordata
            if recorder is not None:
                recorder.add(d, i // s)
            for side, h in robots.items():
                joints[side][i // s] = d.qpos[h.qpos_adr]
        for side, h in robots.items():  # the step towards frame i // s + 1 (its forces were computed at step i)
            f = min(i // s + (i % s > 0 or i == 0), n_frames - 1)
            np.maximum(force[side][f], np.abs(d.actuator_force[h.actuator_ids]), out=force[side][f])
        if states is not None and (i + 1) % s == 0 and (i + 1) // s < n_frames:
            mujoco.mj_getState(layout.model, d, states[(i + 1) // s], INTEGRATION_STATE)
        if on_step is not None:
            on_step(i, d)

    evaluator.step_python(start, inputs, hook)
    pos, quat, vel = layout.object_from_sensors(sensors)
    articulation = layout.parts_from_sensors(sensors, pos, quat)[0] if layout.n_joints else None
    return ReplayRecord(
        object_pose=np.concatenate([pos, quat], axis=1),
        object_vel=vel,
        keypoints={side: sensors[:, h.keypoint_sensor_adrs] for side, h in layout.hands.items()},
        contacts=recorder.columns() if recorder is not None else empty_contact_columns(),
        steps=inputs.shape[0],
        contact_frames=recorder.frames(n_frames) if recorder is not None else None,
        joints=joints,
        joint_force=force,
        command={side: inputs[np.maximum(np.arange(n_frames) * s - 1, 0)][:, h.actuator_ids]
                 for side, h in robots.items()},
        articulation=articulation,
        states=states,
        controls=inputs if record_states else None,
    )


def frame_states(prep: Prepared, start: SimState, n_frames: int) -> FloatArray:
    """(n_frames, state size) zeros but frame 0: ``start`` as ``step_python`` restores it, as an integration
    state (the inputs those of a reset MjData: each step sets its own)."""
    model = prep.layout.model
    data = mujoco.MjData(model)
    start.restore(model, data)
    states = np.zeros((n_frames, mujoco.mj_stateSize(model, INTEGRATION_STATE)))
    mujoco.mj_getState(model, data, states[0], INTEGRATION_STATE)
    return states


@dataclass(frozen=True)
class ReplayJob:
    """One from-scratch replay to run: its keyframes and whether to record contacts."""

    keyframes: dict[str, FloatArray]
    record_contacts: bool = True
    record_states: bool = False


def replay_all(prep: Prepared, start: SimState, jobs: list[ReplayJob], threads: int = 1
               ) -> tuple[list[ReplayRecord], int]:
    """Independent replays from ``start``, each on a fresh MjData of its own, ``threads`` at a time; returns the
    records in ``jobs`` order and the physics steps. ``mj_step`` releases the GIL, so the raw and the refined
    replay of a result overlap on two cores; each starts from the full saved state and warmstart, so its record
    does not depend on where or beside what it ran (the same bits as one after another)."""

    def run(job: ReplayJob) -> tuple[ReplayRecord, int]:
        with ParallelEvaluator(prep.scene.model, 1) as ev:
            rec = replay(prep, ev, start, job.keyframes, record_contacts=job.record_contacts,
                         record_states=job.record_states)
            return rec, ev.stats.steps

    if threads <= 1 or len(jobs) <= 1:
        done = [run(job) for job in jobs]
    else:
        with ThreadPoolExecutor(max_workers=min(threads, len(jobs)), thread_name_prefix="replay") as pool:
            done = list(pool.map(run, jobs))
    return [rec for rec, _ in done], sum(steps for _, steps in done)


def window_problem(prep: Prepared, evaluator: ParallelEvaluator, start: SimState, weights: dict[str, float],
                   lookahead_rotation_weight: float = LOOKAHEAD_ROTATION_WEIGHT) -> SimWindowProblem:
    """The window problem of a prepared sequence (``weights`` empty: the job's own)."""
    return SimWindowProblem(prep.layout, prep.spaces, prep.obj_targets, prep.hand_targets,
                            weights or resolve_weights(prep.options.loss_weights, robot=prep.options.hand is not None),
                            evaluator, start, LOOKAHEAD,
                            lookahead_rotation_weight)
