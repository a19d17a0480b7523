"""CMA-ES populations rolled out on MuJoCo Warp (issue #19 item 5): optional, for machines with a GPU.

``WarpEvaluator`` is a ``ParallelEvaluator`` whose ``rollout`` runs the C candidates as C worlds of one
``mujoco_warp`` data on a Warp device (a CUDA GPU; Warp's CPU device works too, slowly, which is how the tests
run it without a GPU). Everything else stays on the CPU and bit-identical to the CPU path: ``step_python``
(probes, commits, replays) and the result, which ``derive`` replays from scratch in MuJoCo's C engine, so the
object's motion in a result still comes from (CPU) simulation and ``verify`` checks it as before. Only the
ranking of candidates inside CMA-ES sees the GPU rollouts.

What differs from ``mujoco.rollout``: MuJoCo Warp computes in float32, not float64, so a GPU rollout matches
the CPU one closely at first and drifts apart where contacts make the dynamics chaotic
(``bench/gpu_rollout.py`` measures by how much). The recorded arrays keep ``ParallelEvaluator.rollout``'s
layout and convention (the state after each step, the sensors computed at its start), so the losses read
them unchanged.

One rollout is one CUDA graph per step (set the inputs of step s from the uploaded controls, ``mjw.step``,
record, advance s), captured once per population size and replayed n times; the controls go up and the
records come down in one copy each. Contact and constraint buffers that overflow are doubled and the rollout
repeated, so a result never rests on dropped contacts.

Needs the optional packages ``mujoco-warp`` and ``warp-lang`` (``pip install -e .[gpu]``); nothing else imports
this module.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from common.geometry import FloatArray
from worker.refine.evaluator import STATE_SPEC, ParallelEvaluator, SimState, control_size

#: Overflows that mean contacts or constraint rows were dropped (the rollout is then repeated with more room).
#: Solver and line-search iteration limits are not among them: the CPU solver stops at its limits too.
_CAPACITY_OVERFLOWS = int(
    mjw.OverflowType.NEFC | mjw.OverflowType.NJMAX_NNZ | mjw.OverflowType.BROADPHASE
    | mjw.OverflowType.NARROWPHASE | mjw.OverflowType.CCD
)
#: Doublings of ``nconmax`` / ``njmax`` before a rollout gives up (64 -> 4096 contacts per world).
MAX_REGROWTHS = 6


@wp.kernel
def _apply_controls(
    step: wp.array(dtype=int),  # type: ignore[valid-type]
    controls: wp.array3d(dtype=float),  # type: ignore[valid-type]
    nu: int,
    neq: int,
    nmocap: int,
    ctrl: wp.array2d(dtype=float),  # type: ignore[valid-type]
    eq_active: wp.array2d(dtype=bool),  # type: ignore[valid-type]
    mocap_pos: wp.array2d(dtype=wp.vec3),  # type: ignore[valid-type]
    mocap_quat: wp.array2d(dtype=wp.quat),  # type: ignore[valid-type]
) -> None:
    """Step s's inputs from ``controls`` (steps, worlds, ncontrol), in ``CONTROL_SPEC``'s column order: ctrl,
    eq_active, mocap_pos, mocap_quat."""
    w = wp.tid()
    s = step[0]
    for i in range(nu):
        ctrl[w, i] = controls[s, w, i]
    for i in range(neq):
        eq_active[w, i] = controls[s, w, nu + i] > 0.5
    p = nu + neq
    for i in range(nmocap):
        mocap_pos[w, i] = wp.vec3(controls[s, w, p + 3 * i], controls[s, w, p + 3 * i + 1],
                                  controls[s, w, p + 3 * i + 2])
    r = p + 3 * nmocap
    for i in range(nmocap):
        # MuJoCo's w, x, y, z in memory order, as ``mjw.put_data`` stores them.
        mocap_quat[w, i] = wp.quat(controls[s, w, r + 4 * i], controls[s, w, r + 4 * i + 1],
                                   controls[s, w, r + 4 * i + 2], controls[s, w, r + 4 * i + 3])


@wp.kernel
def _record_step(
    step: wp.array(dtype=int),  # type: ignore[valid-type]
    time_: wp.array(dtype=float),  # type: ignore[valid-type]
    qpos: wp.array2d(dtype=float),  # type: ignore[valid-type]
    qvel: wp.array2d(dtype=float),  # type: ignore[valid-type]
    sensordata: wp.array2d(dtype=float),  # type: ignore[valid-type]
    states: wp.array3d(dtype=float),  # type: ignore[valid-type]
    sensors: wp.array3d(dtype=float),  # type: ignore[valid-type]
) -> None:
    """Into ``states`` (steps, worlds, 1 + nq + nv) and ``sensors`` (steps, worlds, nsensordata): the state after
    step s (``STATE_SPEC`` order: time, qpos, qvel) and the sensors computed at its start."""
    w = wp.tid()
    s = step[0]
    nq = qpos.shape[1]
    states[s, w, 0] = time_[w]
    for i in range(nq):
        states[s, w, 1 + i] = qpos[w, i]
    for i in range(qvel.shape[1]):
        states[s, w, 1 + nq + i] = qvel[w, i]
    for i in range(sensordata.shape[1]):
        sensors[s, w, i] = sensordata[w, i]


@wp.kernel
def _advance(step: wp.array(dtype=int)) -> None:  # type: ignore[valid-type]
    step[0] = step[0] + 1


@dataclass
class _Batch:
    """Device buffers for one population size and up to ``capacity`` steps, and the captured step graph."""

    worlds: int
    capacity: int
    data: Any
    step: Any
    controls: Any
    states: Any
    sensors: Any
    graph: Any = None


class WarpEvaluator(ParallelEvaluator):
    """``ParallelEvaluator`` with its batched rollouts on MuJoCo Warp (see the module docstring).

    ``device``: a Warp device ("cuda:0", "cpu"; None: Warp's default). ``nconmax`` / ``njmax``: contacts and
    constraint rows per world to start with (doubled on overflow). ``threads`` sizes only the CPU pool that
    ``step_python`` shares with ``ParallelEvaluator``.
    """

    def __init__(self, model: mujoco.MjModel, threads: int = 1, device: str | None = None,
                 nconmax: int = 64, njmax: int = 512) -> None:
        super().__init__(model, threads)
        wp.init()
        self.device = wp.get_device(device)
        self.nconmax, self.njmax = nconmax, njmax
        self.gpu_steps = 0
        self.regrowths = 0
        # The device copy of ``self.model``, made at the first rollout (a worker's evaluator starts with an
        # empty placeholder model, ``ensure_model`` swaps in each job's).
        self._device_model: Any = None
        self._device_model_of: mujoco.MjModel | None = None
        self._batches: dict[int, _Batch] = {}

    def _put(self) -> None:
        model = self.model
        physics = mujoco.mj_stateSize(model, STATE_SPEC)
        if physics != 1 + model.nq + model.nv:
            raise ValueError("WarpEvaluator needs a model whose full physics state is time, qpos and qvel only "
                             f"(no actuator activations, history or plugins): {physics} != {1 + model.nq + model.nv}")
        self._device_model = mjw.put_model(model)
        # MuJoCo's C solver stops at its iteration limits silently; so may this one (a print per world and step
        # otherwise). Overflows of the contact and row buffers still print, and ``rollout`` repeats those.
        self._device_model.opt.warn_overflow &= ~int(mjw.OverflowType.ITERATIONS | mjw.OverflowType.LS_ITERATIONS)
        self._device_model_of = model
        self._batches = {}

    def rollout(self, start: SimState, control: FloatArray) -> tuple[FloatArray, FloatArray]:
        """As ``ParallelEvaluator.rollout``: (C, n, ncontrol) controls from ``start`` -> states (C, n, nstate),
        sensordata (C, n, nsensordata), in float64 arrays holding MuJoCo Warp's float32 results."""
        m = self.model
        ncontrol = control_size(m)
        if control.ndim != 3 or control.shape[2] != ncontrol:
            raise ValueError(f"control must have shape (C, n, {ncontrol}), got {control.shape}")
        n_cand, n_steps = control.shape[:2]
        t0 = time.perf_counter()
        with wp.ScopedDevice(self.device):
            if self._device_model_of is not m:
                self._put()
            while True:
                batch = self._batch(n_cand, n_steps)
                self._run(batch, start, control)
                overflow = int(np.bitwise_or.reduce(batch.data.overflow.numpy())) & _CAPACITY_OVERFLOWS
                if not overflow:
                    break
                # Contacts or rows were dropped: more room, new buffers and graphs, the same rollout again.
                if self.regrowths >= MAX_REGROWTHS:
                    raise RuntimeError(f"MuJoCo Warp overflow {mjw.OverflowType(overflow)!r} with {self.nconmax} "
                                       f"contacts and {self.njmax} constraint rows per world")
                self.nconmax, self.njmax = 2 * self.nconmax, 2 * self.njmax
                self._batches.clear()
                self.regrowths += 1
            states = np.ascontiguousarray(batch.states.numpy()[:n_steps].transpose(1, 0, 2), dtype=np.float64)
            sensors = np.ascontiguousarray(batch.sensors.numpy()[:n_steps].transpose(1, 0, 2), dtype=np.float64)
        self.stats.add_rollout(n_cand, n_steps, time.perf_counter() - t0)
        self.gpu_steps += n_cand * n_steps
        return states, sensors

    # ------------------------------------------------------------------ device side
    def _batch(self, worlds: int, steps: int) -> _Batch:
        """Buffers for ``worlds`` worlds and at least ``steps`` steps (grown by half again when too short)."""
        batch = self._batches.get(worlds)
        if batch is not None and batch.capacity >= steps:
            return batch
        m = self.model
        capacity = max(steps, int(1.5 * batch.capacity) if batch is not None else steps)
        data = mjw.make_data(m, nworld=worlds, nconmax=self.nconmax, njmax=self.njmax)
        batch = _Batch(
            worlds=worlds,
            capacity=capacity,
            data=data,
            step=wp.zeros(1, dtype=int),
            controls=wp.zeros((capacity, worlds, control_size(m)), dtype=float),
            states=wp.zeros((capacity, worlds, 1 + m.nq + m.nv), dtype=float),
            sensors=wp.zeros((capacity, worlds, max(m.nsensordata, 1)), dtype=float),
        )
        self._batches[worlds] = batch
        return batch

    def _launch_step(self, batch: _Batch) -> None:
        m, d = self.model, batch.data
        wp.launch(_apply_controls, dim=batch.worlds,
                  inputs=[batch.step, batch.controls, m.nu, m.neq, m.nmocap,
                          d.ctrl, d.eq_active, d.mocap_pos, d.mocap_quat])
        mjw.step(self._device_model, d)
        wp.launch(_record_step, dim=batch.worlds,
                  inputs=[batch.step, d.time, d.qpos, d.qvel, d.sensordata, batch.states, batch.sensors])
        wp.launch(_advance, dim=1, inputs=[batch.step])

    def _run(self, batch: _Batch, start: SimState, control: FloatArray) -> None:
        m, d = self.model, batch.data
        n_cand, n_steps = control.shape[:2]
        nq, nv = m.nq, m.nv
        physics = start.physics
        d.time.assign(np.full(n_cand, physics[0], dtype=np.float32))
        d.qpos.assign(np.tile(physics[1 : 1 + nq].astype(np.float32), (n_cand, 1)))
        d.qvel.assign(np.tile(physics[1 + nq : 1 + nq + nv].astype(np.float32), (n_cand, 1)))
        d.qacc_warmstart.assign(np.tile(start.warmstart.astype(np.float32), (n_cand, 1)))
        d.qfrc_applied.zero_()
        d.xfrc_applied.zero_()
        d.overflow.zero_()
        host = np.zeros((batch.capacity, n_cand, control.shape[2]), dtype=np.float32)
        host[:n_steps] = control.transpose(1, 0, 2)
        batch.controls.assign(host)
        batch.step.zero_()
        if batch.graph is None and self.device.is_cuda:
            # The first step runs uncaptured (module loading and any lazy allocation happen there) ...
            self._launch_step(batch)
            batch.step.zero_()
            with wp.ScopedCapture() as capture:
                self._launch_step(batch)
            batch.graph = capture.graph
            # ... and the captured one advanced the step counter: start again from the same state.
            self._run(batch, start, control)
            return
        for _ in range(n_steps):
            if batch.graph is not None:
                wp.capture_launch(batch.graph)
            else:
                self._launch_step(batch)
        wp.synchronize_device(self.device)


__all__ = ["MAX_REGROWTHS", "WarpEvaluator"]
