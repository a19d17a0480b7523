"""The simulation-backed window problem: controls -> rollouts -> recorded frames -> losses.

``SimLayout`` names what the refinement drives and reads in a compiled model (found by the MJCF naming
conventions of ``worker.simulation.hand_mjcf``: actuators ``{side}_{hinge}``, mocap body ``{side}_mocap``, keypoint
``framepos`` sensors ``{side}_kp{j}``), so tests can use tiny inline MJCF models with the same names.
``SimWindowProblem`` implements ``windowed.WindowProblem`` on a ``ParallelEvaluator``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from common.geometry import FloatArray, IntArray, quat_conj, quat_mul, quat_rotate
from worker.refine.controls import HandControlSpace
from worker.refine.evaluator import ParallelEvaluator, SimState, StepHook, control_columns, control_size
from worker.refine.losses import (
    PENETRATION_LIFT_M,
    HandKeypointTargets,
    ObjectTargets,
    WindowRecord,
    window_losses,
)
from worker.refine.spline import keyframe_window
from worker.simulation.scene import held_steps


@dataclass
class HandLayout:
    """Where one hand sits in the rollout arrays: actuators, hinge DoFs, mocap, keypoint sensors, bodies."""

    side: str
    actuator_ids: IntArray  # (H,) in hinge order
    hinge_dof_adrs: IntArray  # (H,)
    mocap_id: int
    keypoint_sensor_adrs: IntArray  # (J, 3) sensordata indices of the keypoint framepos sensors
    body_ids: frozenset[int]
    #: sensordata index of the hand's object-contact distance sensor (-1: the model has none, no penetration)
    penetration_sensor_adr: int = -1

    def penetration(self, sens: FloatArray) -> FloatArray:
        """(...,) the hand's deepest penetration into the object (m, >= 0) from sensordata (..., ns)."""
        if self.penetration_sensor_adr < 0:
            return np.zeros(sens.shape[:-1])
        return np.maximum(-sens[..., self.penetration_sensor_adr], 0.0)


@dataclass
class SimLayout:
    """What the refinement drives and reads. ``object_sensor_adr``: 13 sensordata values from there,
    world framepos (3), framequat (4), framelinvel (3), frameangvel (3) of the object body. ``hold_eq``: the
    weld that holds the object on the steps before frame ``release_frame`` (-1: none;
    ``worker.simulation.scene.Scene.hold_active``)."""

    model: mujoco.MjModel
    substeps: int
    object_body_id: int
    object_sensor_adr: int
    hands: dict[str, HandLayout]
    hold_eq: int = -1
    release_frame: int = 0
    #: An articulated object: ``n_joints`` joint values from ``articulation_sensor_adr`` and, per part beyond the
    #: base, 7 values (position, quaternion of its body frame) from ``part_sensor_adr`` (-1: a rigid object).
    articulation_sensor_adr: int = -1
    n_joints: int = 0
    part_sensor_adr: int = -1

    def parts_from_sensors(self, sens: FloatArray, base_pos: FloatArray, base_quat: FloatArray
                           ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """An articulated object's joint values (..., J) and part poses (..., P, 3) / (..., P, 4), base first,
        from sensordata (..., ns) and the base's body-frame pose (``object_from_sensors``)."""
        a, n = self.articulation_sensor_adr, self.n_joints
        values = sens[..., a : a + n]
        rows = sens[..., self.part_sensor_adr : self.part_sensor_adr + 7 * n].reshape((*sens.shape[:-1], n, 7))
        pos = np.concatenate([base_pos[..., None, :], rows[..., :3]], axis=-2)
        quat = np.concatenate([base_quat[..., None, :], rows[..., 3:]], axis=-2)
        return values, pos, quat

    def equality_switches(self, steps: IntArray) -> FloatArray:
        """(n, neq) ``eq_active`` for global physics steps ``steps``: the model's own, and the object's hold on
        the steps before ``release_frame``'s."""
        m = self.model
        out = np.repeat(m.eq_active0[None].astype(np.float64), len(steps), axis=0)
        if self.hold_eq >= 0:
            out[:, self.hold_eq] = held_steps(steps, self.release_frame, self.substeps)
        return out

    def object_from_sensors(self, sens: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Object body-frame position (..., 3), quaternion (..., 4) and world velocity (..., 6) from sensordata.

        MuJoCo's frame sensors with ``objtype="body"`` measure the body's *inertial* frame (centre of mass,
        principal axes), ``"xbody"`` its body frame; the poses we compare with the data are body-frame poses,
        so an inertial-frame reading is moved back to the body frame here.
        """
        a = self.object_sensor_adr
        pos, quat, lin, ang = sens[..., a : a + 3], sens[..., a + 3 : a + 7], sens[..., a + 7 : a + 10], sens[
            ..., a + 10 : a + 13]
        m = self.model
        sensor = int(np.flatnonzero(m.sensor_adr == a)[0])
        if m.sensor_objtype[sensor] == mujoco.mjtObj.mjOBJ_BODY:
            b = self.object_body_id
            ipos, iquat = m.body_ipos[b], m.body_iquat[b]
            quat = quat_mul(quat, quat_conj(np.broadcast_to(iquat, quat.shape)))  # R_body = R_inertial R_i^T
            offset = quat_rotate(quat, np.broadcast_to(ipos, pos.shape))  # COM - body origin, world
            pos = pos - offset
            lin = lin - np.cross(ang, offset)  # v_origin = v_com + w x (origin - com)
        return pos, quat, np.concatenate([lin, ang], axis=-1)

    @staticmethod
    def from_scene(scene: Any) -> SimLayout:
        """From a ``worker.simulation.scene.Scene``."""
        hands = {
            side: HandLayout(
                side=side,
                actuator_ids=np.asarray(h.actuator_ids),
                hinge_dof_adrs=np.asarray(h.dof_adr),
                mocap_id=int(h.mocap_id),
                keypoint_sensor_adrs=np.asarray(h.keypoint_sensor_adr)[:, None] + np.arange(3),
                body_ids=frozenset(int(b) for b in h.body_ids),
                penetration_sensor_adr=int(h.penetration_sensor_adr),
            )
            for side, h in scene.hands.items()
        }
        return SimLayout(scene.model, scene.substeps_per_frame, scene.object_body_id, scene.object_sensor_adr, hands,
                         scene.object_hold_eq, scene.object_release_frame, scene.object_articulation_sensor_adr,
                         len(scene.object_joint_qpos_adr), scene.object_part_sensor_adr)

    @staticmethod
    def from_model(
        model: mujoco.MjModel, sides: list[str], hinge_names: list[str], object_body: str, substeps: int,
        n_keypoints: int = 21,
    ) -> SimLayout:
        """By the scene's naming conventions (for tiny test models): actuators/joints ``{side}_{hinge}``,
        mocap ``{side}_mocap``, sensors ``{side}_kp{j}`` and ``object_pos`` (followed by quat, linvel, angvel)."""

        def obj_id(kind: mujoco.mjtObj, name: str) -> int:
            i = mujoco.mj_name2id(model, kind, name)
            if i < 0:
                raise ValueError(f"model has no {kind.name} named {name!r}")
            return int(i)

        hands = {}
        for side in sides:
            joints = [obj_id(mujoco.mjtObj.mjOBJ_JOINT, f"{side}_{h}") for h in hinge_names]
            sens = [obj_id(mujoco.mjtObj.mjOBJ_SENSOR, f"{side}_kp{j}") for j in range(n_keypoints)]
            root = int(model.jnt_bodyid[joints[0]])
            while model.body_parentid[root] != 0:
                root = int(model.body_parentid[root])
            hands[side] = HandLayout(
                side=side,
                actuator_ids=np.array([obj_id(mujoco.mjtObj.mjOBJ_ACTUATOR, f"{side}_{h}") for h in hinge_names]),
                hinge_dof_adrs=np.array([int(model.jnt_dofadr[j]) for j in joints]),
                mocap_id=int(model.body_mocapid[obj_id(mujoco.mjtObj.mjOBJ_BODY, f"{side}_mocap")]),
                keypoint_sensor_adrs=np.array([int(model.sensor_adr[s]) + np.arange(3) for s in sens]),
                body_ids=frozenset(b for b in range(model.nbody) if _is_descendant(model, b, root)),
            )
        sensor = obj_id(mujoco.mjtObj.mjOBJ_SENSOR, "object_pos")
        return SimLayout(model, substeps, obj_id(mujoco.mjtObj.mjOBJ_BODY, object_body),
                         int(model.sensor_adr[sensor]), hands)


def _is_descendant(model: mujoco.MjModel, body: int, root: int) -> bool:
    while body > 0:
        if body == root:
            return True
        body = int(model.body_parentid[body])
    return False


#: The key of the one objective over both hands (``SimWindowProblem.combined``).
COMBINED = "both"


class SimWindowProblem:
    """Windowed refinement of one sequence on a compiled model (implements ``windowed.WindowProblem``)."""

    def __init__(
        self,
        layout: SimLayout,
        spaces: dict[str, HandControlSpace],
        obj: ObjectTargets,
        hands: dict[str, HandKeypointTargets],
        weights: dict[str, float],
        evaluator: ParallelEvaluator,
        initial: SimState,
        lookahead: int = 1,
        lookahead_rotation_weight: float = 1.0,
    ) -> None:
        self.layout, self.spaces, self.obj, self.hand_targets = layout, spaces, obj, hands
        self.weights, self.evaluator, self.initial = weights, evaluator, initial
        self.sides = tuple(spaces)
        self.first_window = 1  # keyframe 0 stays zero: the settled frame-0 state is the reference's
        self.lookahead = lookahead
        # Factor on the object's rotation error over the frames past keyframe j + 1 (``keyframe_window``'s
        # lookahead beyond DESIGN §1.6's window), where keyframe j's candidate is held (``replay.LOOKAHEAD``).
        self.lookahead_rotation_weight = lookahead_rotation_weight
        #: Whether the losses are one objective over both hands (``joint_hands.JointHandsProblem``).
        self.combined = False
        first = spaces[self.sides[0]]
        self.n_keyframes = first.n_keyframes
        self.interval, self.substeps, self.num_frames = first.interval, first.substeps, first.num_frames
        m = layout.model
        self._nq, self._nv = m.nq, m.nv
        self._columns = control_columns(m)
        self._ncontrol = control_size(m)
        # [b1, b2]: a contact between bodies b1 and b2 is one between a hand and the object (``probe``).
        self._hand_object_pair = np.zeros((m.nbody, m.nbody), dtype=bool)
        hand_bodies = sorted(frozenset().union(*(h.body_ids for h in layout.hands.values())))
        self._hand_object_pair[layout.object_body_id, hand_bodies] = True
        self._hand_object_pair[hand_bodies, layout.object_body_id] = True
        # The object's height at the settled start: the penetration term's gate (``WindowRecord.lifted``).
        qadr = int(m.jnt_qposadr[m.body_jntadr[layout.object_body_id]])
        self._rest_z = float(initial.physics[1 + qadr + 2])

    # ------------------------------------------------------------------ WindowProblem
    def dim(self, side: str) -> int:
        return self.spaces[side].dim

    def start_state(self) -> SimState:
        return self.initial

    def window(self, j: int) -> tuple[int, int]:
        return keyframe_window(j, self.n_keyframes, self.interval, self.num_frames, self.lookahead)

    def evaluate(
        self, j: int, state: SimState, keyframes: dict[str, FloatArray], candidates: dict[str, FloatArray],
        hold: bool = True,
    ) -> dict[str, FloatArray]:
        f0, f1 = self.window(j)
        control, offsets = self.build_control(keyframes, f0, f1, j, candidates, hold=hold)
        states, sensors = self.evaluator.rollout(state, control)
        rec = self._record(f0, f1, states, sensors, offsets, j)
        return self._losses(rec)

    def _losses(self, rec: WindowRecord) -> dict[str, FloatArray]:
        """Each hand's objective, or with ``combined`` one objective ``COMBINED`` over both hands (the object's
        terms once, plus every hand's terms: ``joint_hands``)."""
        per_hand, terms = window_losses(rec, self.obj, self.hand_targets, self.weights)
        if not self.combined:
            return per_hand
        return {COMBINED: np.asarray(sum(terms.values()), dtype=np.float64)}

    def probe(self, j: int, state: SimState, keyframes: dict[str, FloatArray]) -> tuple[dict[str, float], bool]:
        f0, f1 = self.window(j)
        control, offsets = self.build_control(keyframes, f0, f1)
        touched = False
        m, touching = self.layout.model, self._hand_object_pair

        def hook(i: int, d: mujoco.MjData) -> None:
            nonlocal touched
            if touched or d.ncon == 0:
                return
            bodies = m.geom_bodyid[d.contact.geom[: d.ncon]]  # (ncon, 2): one array lookup, not a loop per contact
            touched = bool(touching[bodies[:, 0], bodies[:, 1]].any())

        # The same rollout as a one-candidate evaluation, stepped in Python to see contacts; only the steps that
        # ``_record`` reads are copied out.
        states, sensors = self._step_recording(state, control[0], hook, self._recorded_steps(f0, f1))
        rec = self._record(f0, f1, states[None], sensors[None], offsets, j)
        return {s: float(v[0]) for s, v in self._losses(rec).items()}, touched

    def commit(self, j: int, state: SimState, keyframes: dict[str, FloatArray]) -> SimState:
        f0, _ = self.window(j)
        f_next = self.window(j + 1)[0] if j + 1 < self.n_keyframes else f0
        if f_next == f0:
            return state
        control, _ = self.build_control(keyframes, f0, f_next, extra_step=False)
        return self.evaluator.step_python(state, control[0])

    # ------------------------------------------------------------------ controls and records
    def build_control(
        self,
        keyframes: dict[str, FloatArray],
        f0: int,
        f1: int,
        j: int | None = None,
        candidates: dict[str, FloatArray] | None = None,
        extra_step: bool = True,
        hold: bool = True,
    ) -> tuple[FloatArray, dict[str, FloatArray]]:
        """Control vectors (C, n, ncontrol) for frames f0 -> f1 and the per-frame offsets (C, F + 1, dim).

        ``extra_step`` adds one substep past f1 so the sensors of frame f1 get recorded (see evaluator); ``hold``
        as in ``HandControlSpace.offsets``.
        """
        s0, s1 = f0 * self.substeps, f1 * self.substeps + (1 if extra_step else 0)
        n = s1 - s0
        # Substep k drives towards the sample at its end, (k + 1) / S (as ``worker.simulation.stepping`` does), and
        # substeps past the last frame hold it.
        idx = np.minimum(np.arange(s0, s1) + 1, self.spaces[self.sides[0]].last_sample)
        n_cand = 1 if candidates is None else len(next(iter(candidates.values())))
        control = np.zeros((n_cand, n, self._ncontrol))
        cols = self._columns
        pos_at, quat_at = cols.mocap_pos.start, cols.mocap_quat.start
        control[:, :, quat_at::4] = 1.0  # identity quaternions for mocap bodies the hands do not drive
        control[:, :, cols.eq_active] = self.layout.equality_switches(np.arange(s0, s1))
        frame_offsets = {}
        for side, space in self.spaces.items():
            h = self.layout.hands[side]
            cand = None if candidates is None else candidates[side]
            offs = space.offsets(keyframes[side], idx, j, cand, hold)
            q, p, r = space.controls(offs, idx)
            control[:, :, h.actuator_ids] = q
            control[:, :, pos_at + 3 * h.mocap_id : pos_at + 3 * h.mocap_id + 3] = p
            control[:, :, quat_at + 4 * h.mocap_id : quat_at + 4 * h.mocap_id + 4] = r
            # Offsets at frames f0 .. f1 for the control-consistency term (differences over f0+1 .. f1).
            fidx = np.arange(f0, f1 + 1) * self.substeps
            frame_offsets[side] = space.offsets(keyframes[side], fidx, j, cand, hold)
        return control, frame_offsets

    def _step_recording(
        self, state: SimState, control: FloatArray, hook: StepHook | None = None, steps: IntArray | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """Python-stepped rollout recording what ``mujoco.rollout`` records (state after, sensors at start), at
        every step or only at ``steps`` (the other rows stay zero)."""
        m = self.layout.model
        nstate = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        states = np.zeros((control.shape[0], nstate))
        sensors = np.zeros((control.shape[0], m.nsensordata))
        wanted = np.zeros(control.shape[0], dtype=bool)
        wanted[slice(None) if steps is None else steps] = True

        def record(i: int, d: mujoco.MjData) -> None:
            if wanted[i]:
                mujoco.mj_getState(m, d, states[i], mujoco.mjtState.mjSTATE_FULLPHYSICS)
                sensors[i] = d.sensordata
            if hook is not None:
                hook(i, d)

        self.evaluator.step_python(state, control, record)
        return states, sensors

    def _recorded_steps(self, f0: int, f1: int) -> IntArray:
        """The rollout steps ``_record`` reads for frames f0+1..f1: the state after, and the sensors of, each."""
        after, at = self._frame_steps(f0, f1)
        return np.union1d(after, at)

    def _frame_steps(self, f0: int, f1: int) -> tuple[IntArray, IntArray]:
        """For frames f0+1..f1 of a rollout from frame f0: the step after which the state is the frame's, and
        the step whose sensors were computed at the frame's state (see the evaluator's convention)."""
        frames = np.arange(f0 + 1, f1 + 1)
        return (frames - f0) * self.substeps - 1, (frames - f0) * self.substeps

    def _record(
        self, f0: int, f1: int, states: FloatArray, sensors: FloatArray, offsets: dict[str, FloatArray],
        j: int | None = None,
    ) -> WindowRecord:
        """Decode frames f0+1..f1 from per-substep states/sensors of the rollout of window j (None: a rollout
        that holds no candidate, every frame weighed alike)."""
        frames = np.arange(f0 + 1, f1 + 1)
        after, at = self._frame_steps(f0, f1)
        sens = sensors[:, at]
        qvel = states[:, after, 1 + self._nq : 1 + self._nq + self._nv]
        obj_pos, obj_quat, obj_vel = self.layout.object_from_sensors(sens)
        arti = part_pos = part_quat = None
        if self.layout.n_joints:
            arti, part_pos, part_quat = self.layout.parts_from_sensors(sens, obj_pos, obj_quat)
        return WindowRecord(
            frames=frames,
            obj_pos=obj_pos,
            obj_quat=obj_quat,
            obj_vel=obj_vel,
            keypoints={side: sens[..., h.keypoint_sensor_adrs] for side, h in self.layout.hands.items()},
            hinge_vel={side: qvel[..., h.hinge_dof_adrs] for side, h in self.layout.hands.items()},
            offsets=offsets,
            penetration={side: h.penetration(sens) for side, h in self.layout.hands.items()},
            lifted=obj_pos[..., 2] > self._rest_z + PENETRATION_LIFT_M,
            rotation_weight=None if j is None else np.where(
                frames > (j + 1) * self.interval, self.lookahead_rotation_weight, 1.0
            ),
            articulation=arti,
            part_pos=part_pos,
            part_quat=part_quat,
        )
