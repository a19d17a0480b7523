"""Parallel candidate evaluation: a pool of MjData driven by ``mujoco.rollout`` (issue #3 item 4).

``ParallelEvaluator`` owns one MjData per thread and a persistent ``mujoco.rollout.Rollout`` thread pool,
so a long-lived worker can keep it across jobs that share a model (``ensure_model``). A batch of open-loop
control sequences (ctrl, equality switches and mocap pose per physics substep, ``control_spec = CTRL | EQ_ACTIVE |
MOCAP_POS | MOCAP_QUAT``, laid out as ``control_columns`` says) is rolled out from one saved state in a C loop; no
Python runs per substep. The equality switches turn the object's hold off when the hand comes
(``worker.simulation.scene.Scene.hold_active``); ``mujoco.rollout`` would otherwise reset them to the model's.

Determinism: every rollout starts from a full physics state *and* an explicit solver warmstart
(``initial_warmstart``), so its result never depends on what the MjData simulated before, nor on which
thread ran it. ``step_python`` is the same integration one substep at a time in Python (used to commit
window states, to record contacts and for the final from-scratch replay); both paths call ``mj_step`` with
identical inputs and give bit-identical states (tested).

Convention: a frame's quantities are those of the state *at* the frame time. ``mujoco.rollout`` records the
state after each step but the sensors computed at the start of that step, i.e. at the state before it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Self

import mujoco
import mujoco.rollout
import numpy as np

from common.geometry import FloatArray

_S = mujoco.mjtState
CONTROL_SPEC = int(_S.mjSTATE_CTRL | _S.mjSTATE_EQ_ACTIVE | _S.mjSTATE_MOCAP_POS | _S.mjSTATE_MOCAP_QUAT)
STATE_SPEC = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)

#: ``step_python`` hook: called with the step index and the MjData right after that step.
StepHook = Callable[[int, mujoco.MjData], None]


@dataclass
class SimState:
    """A committed simulation state: full physics state plus the solver warmstart (qacc_warmstart)."""

    physics: FloatArray  # (mj_stateSize(FULLPHYSICS),)
    warmstart: FloatArray  # (nv,)

    @staticmethod
    def capture(model: mujoco.MjModel, data: mujoco.MjData) -> SimState:
        physics = np.empty(mujoco.mj_stateSize(model, STATE_SPEC))
        mujoco.mj_getState(model, data, physics, STATE_SPEC)
        return SimState(physics, data.qacc_warmstart.copy())

    def restore(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        mujoco.mj_resetData(model, data)
        mujoco.mj_setState(model, data, self.physics, STATE_SPEC)
        data.qacc_warmstart[:] = self.warmstart


@dataclass
class EvalStats:
    """Counters for the result's timings (simulated steps, rollouts, seconds inside simulation)."""

    steps: int = 0
    rollouts: int = 0
    sim_seconds: float = 0.0
    calls: int = 0
    #: The split of ``sim_seconds``/``steps``: batched C rollouts vs substeps stepped from Python.
    rollout_seconds: float = 0.0
    python_seconds: float = 0.0
    python_steps: int = 0

    def plus(self, other: EvalStats) -> EvalStats:
        """The counts of both (a refinement that ran on two models, ``worker.refine.run.RESCUE``)."""
        return EvalStats(**{f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self)})

    def add_rollout(self, candidates: int, steps: int, seconds: float) -> None:
        """Count one batched rollout of ``candidates`` x ``steps`` steps that took ``seconds``."""
        self.sim_seconds += seconds
        self.rollout_seconds += seconds
        self.steps += candidates * steps
        self.rollouts += candidates
        self.calls += 1


def control_size(model: mujoco.MjModel) -> int:
    return int(mujoco.mj_stateSize(model, CONTROL_SPEC))


@dataclass(frozen=True)
class ControlColumns:
    """Where each input sits in a ``CONTROL_SPEC`` vector (MuJoCo's state order): ctrl (nu), eq_active (neq),
    mocap_pos (3 nmocap), mocap_quat (4 nmocap)."""

    ctrl: slice
    eq_active: slice
    mocap_pos: slice
    mocap_quat: slice


def control_columns(model: mujoco.MjModel) -> ControlColumns:
    nu, neq, nm = model.nu, model.neq, model.nmocap
    pos_at = nu + neq
    return ControlColumns(slice(0, nu), slice(nu, pos_at), slice(pos_at, pos_at + 3 * nm),
                          slice(pos_at + 3 * nm, pos_at + 7 * nm))


class ParallelEvaluator:
    """Rolls out batches of control sequences in parallel from one saved state."""

    def __init__(self, model: mujoco.MjModel, threads: int = 1) -> None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        self.threads = threads
        self.stats = EvalStats()
        self._pool: mujoco.rollout.Rollout | None = None
        self.model = model
        self._datas = [mujoco.MjData(model) for _ in range(threads)]
        self._step_data = mujoco.MjData(model)
        self._pool = mujoco.rollout.Rollout(nthread=threads if threads > 1 else 0)

    def ensure_model(self, model: mujoco.MjModel) -> None:
        """Reuse the pool for another job; MjData are re-made only when the model object changes."""
        if model is not self.model:
            self.model = model
            self._datas = [mujoco.MjData(model) for _ in range(self.threads)]
            self._step_data = mujoco.MjData(model)
        self.stats = EvalStats()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def step_data(self) -> mujoco.MjData:
        """A spare MjData for single-threaded Python stepping (commit, contacts, replay)."""
        return self._step_data

    def rollout(self, start: SimState, control: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Roll out (C, n, ncontrol) controls from ``start``: states (C, n, nstate), sensordata (C, n, ns)."""
        if self._pool is None:
            raise RuntimeError("ParallelEvaluator is closed")
        ncontrol = control_size(self.model)
        if control.ndim != 3 or control.shape[2] != ncontrol:
            raise ValueError(f"control must have shape (C, n, {ncontrol}), got {control.shape}")
        n_cand, n_steps = control.shape[:2]
        t0 = time.perf_counter()
        state, sensordata = self._pool.rollout(
            [self.model],
            self._datas,
            start.physics[None],
            np.ascontiguousarray(control),
            control_spec=CONTROL_SPEC,
            initial_warmstart=start.warmstart[None],
        )
        self.stats.add_rollout(n_cand, n_steps, time.perf_counter() - t0)
        return state, sensordata

    def step_python(self, start: SimState, control: FloatArray, on_step: StepHook | None = None) -> SimState:
        """Step (n, ncontrol) controls one by one from ``start`` on the spare MjData; returns the end state.

        ``on_step(i, data)`` runs right after step i (contacts and sensors then describe the state at the
        start of step i).
        """
        m, d = self.model, self._step_data
        start.restore(m, d)
        t0 = time.perf_counter()
        for i in range(control.shape[0]):
            mujoco.mj_setState(m, d, control[i], CONTROL_SPEC)
            mujoco.mj_step(m, d)
            if on_step is not None:
                on_step(i, d)
        elapsed = time.perf_counter() - t0
        self.stats.sim_seconds += elapsed
        self.stats.python_seconds += elapsed
        self.stats.steps += control.shape[0]
        self.stats.python_steps += control.shape[0]
        return SimState.capture(m, d)


