"""Single-threaded rollouts of a ``Scene`` (DESIGN §1.4): initial state, per-substep controls, stepping.

One ``MjData`` per thread: ``rollout`` starts by restoring a saved state, so a rollout from a saved state is
bit-identical whatever that ``MjData`` ran before. In MuJoCo 4.0 ``mjSTATE_FULLPHYSICS`` does *not* hold the
solver warmstart (``qacc_warmstart``), and a stale warmstart changes the result in the last bits; states here
are therefore ``STATE_SPEC = FULLPHYSICS | WARMSTART``. ``rollout`` also accepts a bare FULLPHYSICS state
(``PHYSICS_SPEC``), restoring it with a zero (cold) warmstart — deterministic as well. The object is only
ever placed at frame 0 (``initial_state``); afterwards it moves only through contact, once released from the weld that
holds it until the hand comes (``Scene.hold_active``).

Controls (``substep_controls``): hinge targets and wrist positions are interpolated linearly between frames,
wrist rotations by slerp; substep s of frame f uses the fraction (s + 1) / substeps_per_frame towards frame
f + 1, so the last substep of a frame reaches the next frame's targets exactly. The wrist's mocap track and the
hinge targets are their reference tracks sampled ``SimConfig.wrist_lead_s`` / ``finger_lead_s`` ahead
(``lead_track``, ``lead_values``), so the welded palm and the servoed fingers follow the reference.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from common.geometry import FloatArray, quat_to_matrix, slerp
from worker.hand.reference import HandReference
from worker.simulation.contacts import ContactRecorder
from worker.simulation.metrics import ContactFrames
from worker.simulation.scene import HandHandles, Scene

PHYSICS_SPEC = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
STATE_SPEC = PHYSICS_SPEC | int(mujoco.mjtState.mjSTATE_WARMSTART)


@dataclass
class HandTargets:
    """Per-frame targets of one hand: ``q`` (F,H) its actuated joints (45 hinges for the human hand),
    ``wrist_pos`` (F,3), ``wrist_quat`` (F,4) wxyz."""

    q: FloatArray
    wrist_pos: FloatArray
    wrist_quat: FloatArray

    @classmethod
    def from_reference(cls, ref: HandReference, start: int = 0, end: int | None = None) -> HandTargets:
        sl = slice(start, end)
        return cls(q=ref.q[sl].copy(), wrist_pos=ref.wrist_pos[sl].copy(), wrist_quat=ref.wrist_quat[sl].copy())

    def __post_init__(self) -> None:
        f = self.q.shape[0]
        if self.q.ndim != 2:
            raise ValueError(f"HandTargets.q must have shape (F, H), got {self.q.shape}")
        for name, shape in (("wrist_pos", (f, 3)), ("wrist_quat", (f, 4))):
            if getattr(self, name).shape != shape:
                raise ValueError(f"HandTargets.{name} must have shape {shape}, got {getattr(self, name).shape}")


@dataclass
class Controls:
    """Per-substep inputs: ``ctrl`` (S,nu), ``mocap_pos`` (S,nmocap,3), ``mocap_quat`` (S,nmocap,4)."""

    ctrl: FloatArray
    mocap_pos: FloatArray
    mocap_quat: FloatArray

    @property
    def num_steps(self) -> int:
        return int(self.ctrl.shape[0])


@dataclass
class RolloutRecord:
    """What a rollout recorded per frame (F = steps / substeps_per_frame + 1; frame 0 = the start state).

    ``object_pose`` (F,7) world x y z qw qx qy qz; ``object_vel`` (F,6) linear then angular, world frame;
    ``keypoints`` side -> (F,21,3) world; ``final_state`` full-physics state after the last step; ``states``
    (F, nstate) when requested; ``contacts`` columns (``common.result_format.CONTACT_KEYS``) when requested;
    ``steps`` physics steps taken.
    """

    object_pose: FloatArray
    object_vel: FloatArray
    keypoints: dict[str, FloatArray]
    final_state: FloatArray
    steps: int
    states: FloatArray | None = None
    contacts: dict[str, np.ndarray] | None = None
    #: Per-frame penetration / hand / table flags (``worker.simulation.metrics``).
    contact_frames: ContactFrames | None = None
    #: (F, J) an articulated object's joint values per frame ((F, 0) for a rigid one).
    articulation: FloatArray | None = None




def lead_track(pos: FloatArray, quat: FloatArray, lead_frames: float) -> tuple[FloatArray, FloatArray]:
    """The per-frame wrist track (F,3) / (F,4) sampled ``lead_frames`` ahead, linearly / by slerp, holding
    the last frame: the mocap track under which a welded palm that trails its target by that time follows
    the track itself (``SimConfig.wrist_lead_s``). A lead of 0 returns the track unchanged (bit for bit)."""
    i0, u = _lead_samples(len(pos), lead_frames)
    if u is None:
        return pos.copy(), quat.copy()
    return lead_values(pos, lead_frames), slerp(quat[i0], quat[i0 + 1], u)


def lead_values(values: FloatArray, lead_frames: float) -> FloatArray:
    """A per-frame track (F, ...) sampled ``lead_frames`` ahead, linearly, holding the last frame (the hinge
    targets' lead, ``SimConfig.finger_lead_s``). A lead of 0 returns the track unchanged (bit for bit)."""
    i0, u = _lead_samples(len(values), lead_frames)
    if u is None:
        return values.copy()
    w = u.reshape((-1,) + (1,) * (values.ndim - 1))
    return np.asarray((1 - w) * values[i0] + w * values[i0 + 1])


def _lead_samples(n: int, lead_frames: float) -> tuple[np.ndarray, FloatArray | None]:
    """Left sample index and fraction of every frame moved ``lead_frames`` ahead (None: nothing to move)."""
    if lead_frames < 0:
        raise ValueError(f"lead_frames must be >= 0, got {lead_frames}")
    if lead_frames == 0 or n < 2:
        return np.arange(n), None
    times = np.minimum(np.arange(n) + lead_frames, n - 1)
    i0 = np.minimum(np.floor(times).astype(np.int64), n - 2)
    return i0, times - i0


def substep_controls(scene: Scene, targets: Mapping[Any, HandTargets]) -> Controls:
    """Per-substep controls taking the hands from frame 0 to frame F-1 of ``targets`` ((F-1)·spf steps)."""
    model = scene.model
    missing = set(scene.hands) - set(targets)
    if missing:
        raise ValueError(f"targets lack hands {sorted(missing)}")
    frames = {t.q.shape[0] for t in targets.values()}
    if len(frames) != 1 or min(frames) < 2:
        raise ValueError(f"every hand needs the same number (>= 2) of target frames, got {sorted(frames)}")
    n_frames = frames.pop()
    spf = scene.substeps_per_frame
    steps = (n_frames - 1) * spf
    f = np.repeat(np.arange(n_frames - 1), spf)
    alpha = np.tile((np.arange(spf) + 1.0) / spf, n_frames - 1)
    ctrl = np.zeros((steps, model.nu))
    mocap_pos = np.zeros((steps, model.nmocap, 3))
    mocap_quat = np.zeros((steps, model.nmocap, 4))
    mocap_quat[..., 0] = 1.0
    lead, finger_lead = scene.config.lead_frames(spf)
    for side, h in scene.hands.items():
        t = targets[side]
        hinge = lead_values(t.q, finger_lead)
        q = (1 - alpha)[:, None] * hinge[f] + alpha[:, None] * hinge[f + 1]
        lower, upper = joint_bounds(h)
        ctrl[:, h.actuator_ids] = np.clip(q, lower, upper)
        wrist_pos, wrist_quat = lead_track(t.wrist_pos, t.wrist_quat, lead)
        mocap_pos[:, h.mocap_id] = (1 - alpha)[:, None] * wrist_pos[f] + alpha[:, None] * wrist_pos[f + 1]
        mocap_quat[:, h.mocap_id] = slerp(wrist_quat[f], wrist_quat[f + 1], alpha)
    return Controls(ctrl=ctrl, mocap_pos=mocap_pos, mocap_quat=mocap_quat)


def joint_bounds(h: HandHandles) -> tuple[FloatArray, FloatArray]:
    """The actuated joints' limits of a hand (the human hand's are ``JOINT_LOWER`` / ``JOINT_UPPER``)."""
    return h.q_limits[:, 0], h.q_limits[:, 1]


def state_size(scene: Scene, spec: int = STATE_SPEC) -> int:
    return int(mujoco.mj_stateSize(scene.model, spec))


def get_state(scene: Scene, data: mujoco.MjData, spec: int = STATE_SPEC) -> FloatArray:
    out = np.empty(state_size(scene, spec))
    mujoco.mj_getState(scene.model, data, out, spec)
    return out


def set_state(scene: Scene, data: mujoco.MjData, state: FloatArray) -> None:
    """Restore a ``STATE_SPEC`` state, or a ``PHYSICS_SPEC`` one with a cold (zero) warmstart."""
    state = np.asarray(state, dtype=np.float64)
    if state.shape == (state_size(scene, STATE_SPEC),):
        mujoco.mj_setState(scene.model, data, state, STATE_SPEC)
    elif state.shape == (state_size(scene, PHYSICS_SPEC),):
        mujoco.mj_setState(scene.model, data, state, PHYSICS_SPEC)
        data.qacc_warmstart[:] = 0.0
    else:
        raise ValueError(
            f"state must have {state_size(scene)} (or {state_size(scene, PHYSICS_SPEC)}) values, got {state.shape}"
        )


def pose_hands(scene: Scene, data: mujoco.MjData, targets: Mapping[Any, HandTargets], frame: int = 0) -> None:
    """Put every hand exactly at its target pose of ``frame`` (root, hinges, mocap and servo targets)."""
    for side, h in scene.hands.items():
        t = targets[side]
        q = np.clip(t.q[frame], *joint_bounds(h))
        data.qpos[h.root_qpos_adr : h.root_qpos_adr + 3] = t.wrist_pos[frame]
        data.qpos[h.root_qpos_adr + 3 : h.root_qpos_adr + 7] = t.wrist_quat[frame]
        data.qpos[h.qpos_adr] = q
        data.ctrl[h.actuator_ids] = q
        data.mocap_pos[h.mocap_id] = t.wrist_pos[frame]
        data.mocap_quat[h.mocap_id] = t.wrist_quat[frame]


def initial_state(
    scene: Scene, data: mujoco.MjData, targets: Mapping[Any, HandTargets], with_warmstart: bool = False
) -> tuple[FloatArray, int]:
    """The frame-0 state: hands at their frame-0 targets, object at ``scene.object_init_pose`` at rest, then
    ``config.settle_seconds`` of simulation with the hands held (the object settles on the table by physics
    alone, or stays held where it starts when the scene holds it until the hand comes, ``Scene.hold_active``).
    Returns (state with time reset to 0, settle steps taken); the state is ``PHYSICS_SPEC`` (FULLPHYSICS)
    by default — ``data.qacc_warmstart`` then holds the settled warmstart — or ``STATE_SPEC`` with
    ``with_warmstart``."""
    place_start(scene, data, targets)
    n_settle = settle_placed(scene, data)
    return get_state(scene, data, STATE_SPEC if with_warmstart else PHYSICS_SPEC), n_settle


def place_start(scene: Scene, data: mujoco.MjData, targets: Mapping[Any, HandTargets]) -> None:
    """``data`` reset to the state the settling starts from: hands at their frame-0 targets, the object at
    ``scene.object_init_pose`` at rest, the hold weld on where the scene has one."""
    model = scene.model
    mujoco.mj_resetData(model, data)
    pose_hands(scene, data, targets, 0)
    a = scene.object_qpos_adr
    data.qpos[a : a + 7] = scene.object_init_pose
    if scene.articulated:
        data.qpos[scene.object_joint_qpos_adr] = scene.object_init_articulation
    if scene.object_hold_eq >= 0:  # the object rests where it starts until the hand comes (``SimConfig.hold_until_m``)
        data.eq_active[scene.object_hold_eq] = 1
    mujoco.mj_forward(model, data)


def settle_placed(scene: Scene, data: mujoco.MjData) -> int:
    """``config.settle_seconds`` of simulation from the state in ``data`` (``place_start``'s, or one loaded), the
    inputs as they are; then time reset to 0 and the hold weld back to its default. Returns the steps taken."""
    model = scene.model
    n_settle = round(scene.config.settle_seconds / model.opt.timestep)
    for _ in range(n_settle):
        mujoco.mj_step(model, data)
    data.time = 0.0
    if scene.object_hold_eq >= 0:  # not part of the state: the rollouts switch it step by step
        data.eq_active[scene.object_hold_eq] = model.eq_active0[scene.object_hold_eq]
    return n_settle


def _record_frame(scene: Scene, data: mujoco.MjData, rec: dict[str, FloatArray], i: int) -> None:
    a, d = scene.object_qpos_adr, scene.object_dof_adr
    rec["pose"][i] = data.qpos[a : a + 7]
    rot = quat_to_matrix(data.qpos[a + 3 : a + 7])
    rec["vel"][i, :3] = data.qvel[d : d + 3]
    rec["vel"][i, 3:] = rot @ data.qvel[d + 3 : d + 6]  # free-joint angular velocity is in the body frame
    for side, h in scene.hands.items():
        rec[side][i] = data.site_xpos[h.keypoint_site_ids]
    rec["articulation"][i] = data.qpos[scene.object_joint_qpos_adr]


def rollout(
    scene: Scene,
    data: mujoco.MjData,
    state: FloatArray,
    ctrl: FloatArray,
    mocap_pos: FloatArray,
    mocap_quat: FloatArray,
    record_contacts: bool = False,
    record_states: bool = False,
    frame_offset: int = 0,
) -> RolloutRecord:
    """Step from ``state`` through the S substeps of ``ctrl`` (S,nu) / ``mocap_pos`` (S,nmocap,3) /
    ``mocap_quat`` (S,nmocap,4); record every ``substeps_per_frame`` steps (see ``RolloutRecord``).

    Contacts of a frame are those of its last substep (solved forces); their frame numbers are
    ``frame_offset + i``; the object is held on the steps ``Scene.hold_active`` says. Keypoints and object pose
    are read after a kinematics pass at the frame's state.
    """
    model = scene.model
    steps = ctrl.shape[0]
    spf = scene.substeps_per_frame
    if ctrl.shape != (steps, model.nu):
        raise ValueError(f"ctrl must have shape (S, {model.nu}), got {ctrl.shape}")
    if mocap_pos.shape != (steps, model.nmocap, 3):
        raise ValueError(f"mocap_pos must have shape ({steps}, {model.nmocap}, 3), got {mocap_pos.shape}")
    if mocap_quat.shape != (steps, model.nmocap, 4):
        raise ValueError(f"mocap_quat must have shape ({steps}, {model.nmocap}, 4), got {mocap_quat.shape}")
    if steps % spf:
        raise ValueError(f"ctrl must cover whole frames: {steps} steps is not a multiple of {spf}")
    n_frames = steps // spf + 1
    rec: dict[str, FloatArray] = {"pose": np.zeros((n_frames, 7)), "vel": np.zeros((n_frames, 6)),
                                  "articulation": np.zeros((n_frames, len(scene.object_joint_qpos_adr)))}
    for side, h in scene.hands.items():
        rec[side] = np.zeros((n_frames, len(h.keypoint_site_ids), 3))
    states = np.zeros((n_frames, state_size(scene))) if record_states else None
    recorder = ContactRecorder(scene) if record_contacts else None

    set_state(scene, data, state)
    if recorder is not None:
        mujoco.mj_forward(model, data)  # frame-0 contacts; the state is restored below (forward is not pure)
        recorder.add(data, frame_offset)
        set_state(scene, data, state)
    mujoco.mj_kinematics(model, data)
    _record_frame(scene, data, rec, 0)
    if states is not None:
        states[0] = state
    held = scene.hold_active(frame_offset * spf + np.arange(steps))
    for s in range(steps):
        data.ctrl[:] = ctrl[s]
        data.mocap_pos[:] = mocap_pos[s]
        data.mocap_quat[:] = mocap_quat[s]
        if scene.object_hold_eq >= 0:
            data.eq_active[scene.object_hold_eq] = held[s]
        mujoco.mj_step(model, data)
        if (s + 1) % spf == 0:
            i = (s + 1) // spf
            if recorder is not None:
                recorder.add(data, frame_offset + i)
            if states is not None:
                mujoco.mj_getState(model, data, states[i], STATE_SPEC)
            mujoco.mj_kinematics(model, data)
            _record_frame(scene, data, rec, i)
    return RolloutRecord(
        object_pose=rec["pose"],
        object_vel=rec["vel"],
        keypoints={side: rec[side] for side in scene.hands},
        final_state=get_state(scene, data),
        steps=steps,
        states=states,
        contacts=None if recorder is None else recorder.columns(),
        contact_frames=None if recorder is None or frame_offset else recorder.frames(n_frames),
        articulation=rec["articulation"],
    )
