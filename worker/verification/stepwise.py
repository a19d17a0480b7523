"""Stepwise verification (issue #54 item 1): every stored frame follows from the stored frame before it.

A result stores the full integration state (``worker.refine.replay.INTEGRATION_STATE``: time, qpos, qvel, act,
the solver warmstart, ctrl, applied forces, equality switches, mocap poses, userdata, plugin state) of its refined
and its raw replay at every frame, and the inputs it set before every physics step. ``replay_stepwise`` first
checks the stored inputs against those the keyframes give here (through the same ``build_control`` as the
refinement: NumPy's kernels make them differ in their last bits, 1e-13, between hosts), then runs the replay again
from the stored frame-0 state under the *stored* inputs, and at the end of every frame compares the state it
reached with the stored one and then *loads the stored one* before going on. So each comparison covers one frame's
physics steps from an exactly known state under exactly known inputs: MuJoCo is deterministic given both, and
what is left to differ (the model's numbers) grows over one frame to far below a micrometre, where a whole rollout
through contact grows it to millimetres. Under recomputed inputs (results stored before the inputs were) a
last-bit difference in them can decide a contact event and move a frame by a fraction of a milliradian. The
records the replay makes along the way (sensors, contacts, keypoints of each frame, computed at the stored states)
are what the result's arrays and figures are then checked against, tightly, on any host.

What a state may not do: hold an applied force (``qfrc_applied``, ``xfrc_applied``, userdata must be zero: the
object moves only through contact), carry inputs other than the controls the keyframes give (ctrl, mocap pose,
equality switches), or differ from where the frame before it leads (a teleported object, a hand moved off its
controls, a changed velocity or warmstart). Each failure names the replay's array, the state field, the frame
and the degree of freedom.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np

from common.geometry import FloatArray
from common.result_format import PRESETTLE_STATE_KEY
from worker.refine.derive import CONTROL_KEYS, STATE_KEYS, Derived, build_arrays, replay_metrics
from worker.refine.evaluator import ParallelEvaluator, SimState
from worker.refine.prepare import Prepared, presettle_state, settled_from, settled_start
from worker.refine.replay import INTEGRATION_STATE, ReplayRecord, frame_states, replay, replay_control

if TYPE_CHECKING:
    from worker.verification.report import VerifyReport

_S = mujoco.mjtState
#: The integration state's parts in the order MuJoCo lays them out (the order of their bits).
STATE_FIELDS: tuple[tuple[str, int], ...] = (
    ("time", int(_S.mjSTATE_TIME)), ("qpos", int(_S.mjSTATE_QPOS)), ("qvel", int(_S.mjSTATE_QVEL)),
    ("act", int(_S.mjSTATE_ACT)), ("qacc_warmstart", int(_S.mjSTATE_WARMSTART)), ("ctrl", int(_S.mjSTATE_CTRL)),
    ("qfrc_applied", int(_S.mjSTATE_QFRC_APPLIED)), ("xfrc_applied", int(_S.mjSTATE_XFRC_APPLIED)),
    ("eq_active", int(_S.mjSTATE_EQ_ACTIVE)), ("mocap_pos", int(_S.mjSTATE_MOCAP_POS)),
    ("mocap_quat", int(_S.mjSTATE_MOCAP_QUAT)), ("userdata", int(_S.mjSTATE_USERDATA)),
    ("plugin_state", int(_S.mjSTATE_PLUGIN)),
)
#: Parts that must be zero in every stored state: forces from outside the simulation.
FORCE_FIELDS = ("qfrc_applied", "xfrc_applied", "userdata")
#: Parts the controls set before every step: compared with the controls of the step that ended the frame.
INPUT_FIELDS = ("ctrl", "eq_active", "mocap_pos", "mocap_quat")
#: Parts the physics integrates: compared with where the frame before leads.
PHYSICS_FIELDS = ("time", "qpos", "qvel", "act", "qacc_warmstart", "plugin_state")


@dataclass(frozen=True)
class StateTolerances:
    """How far a stored frame's state may be from the state one frame's steps reach from the stored frame before
    it (max abs per degree of freedom; positions by ``mj_differentiatePos``: metres and radians), and how far the
    running sums of those deviations may go (``running_qpos`` / ``running_qvel``, signed, per degree of freedom).

    Measured (``bench/results/verify_portable.md``): with other NumPy/OpenBLAS kernels forced, an honest frame is
    reached within ~1e-12 m / rad and mostly ~1e-10 m/s, with rare spikes to ~3e-8 m/s where a contact's solve
    takes another path (the controls differ in their last bits, 1e-15); the per-frame bounds leave a margin of
    ~1000 over those. A forger could nudge every frame within them, and nudges add up: the running sums bound what
    they add up to, the displacement injected to ``running_qpos`` and the velocity to ``running_qvel``, so over T
    seconds an object strays at most ``running_qpos + running_qvel * T`` (60 micrometres over 5 s, 1 mm over the
    100 s of the service's 3000-frame limit at 30 fps), where the whole-rollout check allowed 5 mm + 10 % of the
    tracking error per frame. Frame 0 is compared with a start settled afresh here (a rollout of its own, where
    last bits grow over the settling steps), ``start`` times more (measured: 6e-11 m, 8e-10 m/s)."""

    qpos: float = 1e-6  # m / rad
    qvel: float = 1e-5  # m/s / rad/s
    qacc_warmstart: float = 1e-4  # m/s^2 / rad/s^2: only the solver's first guess
    act: float = 1e-6
    time: float = 1e-12  # s
    plugin_state: float = 1e-6
    inputs: float = 1e-9  # ctrl (rad), mocap pose (m, unit quaternion), equality switches against the controls
    running_qpos: float = 1e-5  # m / rad: the signed sum of the per-frame qpos deviations, any frame, any dof
    running_qvel: float = 1e-5  # m/s / rad/s
    start: float = 10.0  # frame 0's factor (against the re-settled start)

    def of(self, name: str, frame: int = 1) -> float:
        base = self.inputs if name in INPUT_FIELDS else float(getattr(self, name))
        return base * (self.start if frame == 0 and name in PHYSICS_FIELDS else 1.0)


STATE_TOLERANCES = StateTolerances()


@dataclass
class Deviation:
    """The largest deviation of one state field over a replay: value, frame and the degree of freedom."""

    value: float = 0.0
    frame: int = -1
    where: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "frame": self.frame, "where": self.where}


@dataclass
class StepwiseReport:
    """One replay's stepwise check (``replay_stepwise``)."""

    key: str  # the result array holding the states (``worker.refine.derive.STATE_KEYS``)
    frames: int = 0
    exact: bool = False  # every frame reached bit for bit
    #: state field -> its largest deviation over frames 1.. (each from the stored frame before it)
    largest: dict[str, Deviation] = field(default_factory=dict)
    #: state field -> frame 0's deviation from the start re-settled here (the settling is a rollout of its own)
    start: dict[str, Deviation] = field(default_factory=dict)
    #: "running_qpos" / "running_qvel" -> the largest |signed sum of the per-frame deviations| up to a frame
    running: dict[str, Deviation] = field(default_factory=dict)
    failures: list[str] = field(default_factory=list)
    seconds: float = 0.0
    steps: int = 0
    #: The stored inputs' largest deviation from the keyframes' (None: the result stores none, the replay stepped
    #: under the inputs made here).
    controls: Deviation | None = None
    #: The stored pre-settle state's largest deviation from the start placed here (None: none stored, frame 0
    #: compared with a start settled afresh here).
    presettle: Deviation | None = None

    def worst(self) -> tuple[str, Deviation]:
        """The field whose largest deviation is furthest towards its tolerance (for a one-line summary)."""
        if not self.largest:
            return "", Deviation()
        name = max(self.largest, key=lambda k: self.largest[k].value / max(STATE_TOLERANCES.of(k), 1e-300))
        return name, self.largest[name]

    def to_dict(self) -> dict[str, Any]:
        return {"key": self.key, "frames": self.frames, "exact": self.exact, "seconds": self.seconds,
                "steps": self.steps, "largest": {k: v.to_dict() for k, v in self.largest.items()},
                "start": {k: v.to_dict() for k, v in self.start.items()},
                "running": {k: v.to_dict() for k, v in self.running.items()},
                "controls": None if self.controls is None else self.controls.to_dict(),
                "presettle": None if self.presettle is None else self.presettle.to_dict(),
                "failures": list(self.failures)}


class StateLayout:
    """Where each part sits in an integration state of ``model``, and a name for each of its entries."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.size = int(mujoco.mj_stateSize(model, INTEGRATION_STATE))
        self.slices: dict[str, slice] = {}
        at = 0
        for name, bit in STATE_FIELDS:
            n = int(mujoco.mj_stateSize(model, bit))
            self.slices[name] = slice(at, at + n)
            at += n
        assert at == self.size, (at, self.size)
        self._dof = [self._dof_name(j) for j in range(model.nv)]

    def _dof_name(self, dof: int) -> str:
        m = self.model
        joint = int(m.dof_jntid[dof])
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, joint) or f"joint {joint}"
        if m.jnt_type[joint] == mujoco.mjtJoint.mjJNT_FREE:
            k = dof - int(m.jnt_dofadr[joint])
            return f"{name} {'xyz'[k % 3]} {'position' if k < 3 else 'rotation'}"
        return name

    def part(self, states: FloatArray, name: str) -> FloatArray:
        return np.asarray(states[..., self.slices[name]])

    def entry(self, name: str, index: int) -> str:
        """A readable name of entry ``index`` of part ``name``."""
        m = self.model
        if name in ("qpos", "qvel", "qacc_warmstart", "qfrc_applied"):
            return self._dof[index] if index < m.nv else str(index)
        if name in ("mocap_pos", "mocap_quat"):
            size, axes = (3, "xyz") if name == "mocap_pos" else (4, "wxyz")
            body_id = int(np.flatnonzero(m.body_mocapid == index // size)[0])
            body = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, body_id) or f"body {body_id}"
            return f"{body} {axes[index % size]}"
        if name == "ctrl":
            return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, index) or f"actuator {index}"
        if name == "xfrc_applied":
            body = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, index // 6) or f"body {index // 6}"
            return f"{body} {'force' if index % 6 < 3 else 'torque'}"
        if name == "eq_active":
            return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_EQUALITY, index) or f"equality {index}"
        return f"{index}"

    def differences(self, stored: FloatArray, reached: FloatArray) -> dict[str, FloatArray]:
        """Per part, stored - reached per entry (signed); qpos in the tangent space (one value per degree of
        freedom: metres, radians), so a quaternion's sign does not count and a rotation reads in radians."""
        out = {}
        for name, sl in self.slices.items():
            if name == "qpos":
                dq = np.zeros(self.model.nv)
                mujoco.mj_differentiatePos(self.model, dq, 1.0, reached[sl], stored[sl])
                out[name] = dq
            else:
                out[name] = stored[sl] - reached[sl]
        return out


def replay_stepwise(
    prep: Prepared, keyframes: dict[str, FloatArray], states: FloatArray, key: str,
    tol: StateTolerances = STATE_TOLERANCES, record_contacts: bool = True,
    controls: FloatArray | None = None, controls_key: str = "", presettle: FloatArray | None = None,
) -> tuple[StepwiseReport, ReplayRecord]:
    """The replay of ``keyframes`` checked frame by frame against the stored ``states`` (F, state size) of result
    array ``key``, stepping under the stored ``controls`` (steps, ncontrol) of array ``controls_key`` once they
    match the keyframes' (None: under the keyframes'); see the module docstring. Returns the report and the record
    made at the stored states. ``presettle`` (checked by ``checked_presettle``): frame 0 is compared with the
    settling from it, as tightly as any other frame; without it, with the start settled afresh here."""
    model = prep.layout.model
    layout = StateLayout(model)
    report = StepwiseReport(key, frames=int(prep.num_frames))
    n, spf = prep.num_frames, prep.layout.substeps
    states = np.asarray(states)
    if states.shape != (n, layout.size) or states.dtype != np.float64:
        report.failures.append(f"{key}: shape {states.shape} {states.dtype}, the model's integration state is "
                               f"({n}, {layout.size}) float64")
        return report, _empty_record()
    _check_forces(report, layout, states, key)
    with ParallelEvaluator(model, 1) as ev:  # the re-settled frame 0 the replay started from
        if presettle is None:
            start, _ = settled_start(prep, ev)
        else:  # the settling is steps like any frame's: from the same state, the same bits
            start, tol = settled_from(prep, ev, presettle), replace(tol, start=1.0)
        expected_inputs = replay_control(prep, ev, start, keyframes)
    inputs = None
    if controls is not None:
        inputs = _checked_controls(report, layout, np.asarray(controls), expected_inputs, controls_key, tol,
                                   prep.layout.substeps)
        if inputs is None:
            return report, _empty_record()
    expected0 = frame_states(prep, start, 1)[0]
    loaded = mujoco.MjData(model)
    mujoco.mj_setState(model, loaded, states[0], INTEGRATION_STATE)

    def load_stored(i: int, d: mujoco.MjData) -> None:
        if (i + 1) % spf == 0 and (i + 1) // spf < n:  # frame (i + 1) // spf reached: recorded; go on from the stored
            mujoco.mj_setState(model, d, states[(i + 1) // spf], INTEGRATION_STATE)

    t0 = time.perf_counter()
    with ParallelEvaluator(model, 1) as ev:
        rec = replay(prep, ev, SimState.capture(model, loaded), keyframes, record_contacts=record_contacts,
                     on_step=load_stored, record_states=True, control=inputs)
        report.steps = ev.stats.steps
    report.seconds = time.perf_counter() - t0
    assert rec.states is not None
    reached = rec.states.copy()
    reached[0] = expected0  # frame 0 follows from the settling: the re-settled start
    _compare(report, layout, states, reached, key, tol)
    return report, rec


def checked_presettle(prep: Prepared, stored: FloatArray, tol: StateTolerances = STATE_TOLERANCES
                      ) -> tuple[FloatArray | None, Deviation, list[str]]:
    """The stored pre-settle state to settle from, if it is the start placed here (``presettle_state``: the hands
    at their frame-0 targets, the object at its recorded pose) within ``tol.inputs`` in every part; its largest
    deviation; the failures naming part and entry where it is not."""
    layout = StateLayout(prep.layout.model)
    key = PRESETTLE_STATE_KEY
    stored = np.asarray(stored)
    if stored.shape != (layout.size,) or stored.dtype != np.float64 or not np.all(np.isfinite(stored)):
        return None, Deviation(), [f"{key}: shape {stored.shape} {stored.dtype} (finite: "
                                   f"{bool(np.all(np.isfinite(stored)))}), the model's integration state is "
                                   f"({layout.size},) float64"]
    worst, failures = Deviation(), []
    for name, signed in layout.differences(stored, presettle_state(prep)).items():
        if not signed.size:
            continue
        i = int(np.argmax(np.abs(signed)))
        here = Deviation(float(abs(signed[i])), 0, f"{name} {layout.entry(name, i)}")
        worst = here if here.value > worst.value else worst
        if here.value > tol.inputs:
            failures.append(f"{key}.{name}: {here.value:.6g} from the start placed here ({layout.entry(name, i)}; "
                            f"tolerance {tol.inputs:g}): frame 0 must settle from the recorded start")
    return (None if failures else stored), worst, failures


def _checked_controls(report: StepwiseReport, layout: StateLayout, stored: FloatArray, expected: FloatArray,
                      key: str, tol: StateTolerances, substeps: int) -> FloatArray | None:
    """The stored inputs to step under, if they are the keyframes' within ``tol.inputs`` (their deviation into
    ``report.controls``); None, with a failure naming the step's frame and the input, if they are not."""
    if stored.shape != expected.shape or stored.dtype != np.float64:
        report.failures.append(f"{key}: shape {stored.shape} {stored.dtype}, the replay's inputs are "
                               f"{expected.shape} float64")
        return None
    if not np.all(np.isfinite(stored)):
        step, col = (int(v) for v in np.argwhere(~np.isfinite(stored))[0])
        report.failures.append(f"{key}: not a finite number at frame {step // substeps} "
                               f"(step {step}; {_control_entry(layout, col)})")
        return None
    diff = np.abs(stored - expected)
    step, col = (int(v) for v in np.unravel_index(int(np.argmax(diff)), diff.shape))
    report.controls = Deviation(float(diff[step, col]), step // substeps, _control_entry(layout, col))
    if report.controls.value > tol.inputs:
        bad = np.argwhere(diff > tol.inputs)[0]
        first = Deviation(float(diff[bad[0], bad[1]]), int(bad[0]) // substeps, _control_entry(layout, int(bad[1])))
        report.failures.append(
            f"{key}: {first.value:.6g} from the keyframes' inputs at frame {first.frame} (step {int(bad[0])}; "
            f"{first.where}; tolerance {tol.inputs:g}); largest {report.controls.value:.6g} at frame "
            f"{report.controls.frame} ({report.controls.where})")
        return None
    return stored


def _control_entry(layout: StateLayout, column: int) -> str:
    """A readable name of column ``column`` of a replay's inputs (``CONTROL_SPEC``: ctrl, equality switches,
    mocap positions, mocap quaternions: the integration state's input parts in the same order)."""
    at = 0
    for name in ("ctrl", "eq_active", "mocap_pos", "mocap_quat"):
        n = layout.slices[name].stop - layout.slices[name].start
        if column < at + n:
            return f"{name} {layout.entry(name, column - at)}"
        at += n
    return f"column {column}"


def _check_forces(report: StepwiseReport, layout: StateLayout, states: FloatArray, key: str) -> None:
    """No applied force in any stored state, and no value that is not a finite number."""
    bad = np.argwhere(~np.isfinite(states))
    if bad.size:
        frame, index = (int(v) for v in bad[0])
        name = next(n for n, sl in layout.slices.items() if sl.start <= index < sl.stop)
        report.failures.append(f"{key}.{name}: not a finite number at frame {frame} "
                               f"({layout.entry(name, index - layout.slices[name].start)})")
    for name in FORCE_FIELDS:
        part = layout.part(states, name)
        if part.size and np.any(part != 0):
            frame, index = np.argwhere(part != 0)[0]
            report.failures.append(
                f"{key}.{name}: {float(part[frame, index]):.6g} at frame {int(frame)} "
                f"({layout.entry(name, int(index))}); must be zero: the object moves only through contact and the "
                "hand only through its controls")


def _compare(report: StepwiseReport, layout: StateLayout, stored: FloatArray, reached: FloatArray, key: str,
             tol: StateTolerances) -> None:
    """Every frame's state against the state reached; per field the largest deviation, and a failure naming the
    first frame beyond the tolerance (where the forgery starts) and the largest."""
    report.exact = bool(np.array_equal(stored, reached))
    first: dict[str, Deviation] = {}
    running = {"qpos": np.zeros(layout.model.nv), "qvel": np.zeros(layout.model.nv)}
    for f in range(len(stored)):
        for name, signed in layout.differences(stored[f], reached[f]).items():
            if name in FORCE_FIELDS or not signed.size:
                continue
            if name in running and f > 0:  # what the nudges add up to (the start is a state of its own)
                running[name] += signed
                j = int(np.argmax(np.abs(running[name])))
                sum_name = f"running_{name}"
                total = Deviation(float(abs(running[name][j])), f, layout.entry(name, j))
                if total.value > report.running.setdefault(sum_name, Deviation()).value:
                    report.running[sum_name] = total
                if total.value > getattr(tol, sum_name) and sum_name not in first:
                    first[sum_name] = total
            d = np.abs(signed)
            i = int(np.argmax(d))
            here = Deviation(float(d[i]), f, layout.entry(name, i))
            where = report.start if f == 0 else report.largest
            if here.value > where.setdefault(name, Deviation()).value:
                where[name] = here
            if here.value > tol.of(name, f) and name not in first:
                first[name] = here
    for name, dev in first.items():
        if name.startswith("running_"):
            field_name = name[len("running_"):]
            report.failures.append(
                f"{key}.{field_name}: the per-frame deviations add up to {dev.value:.6g} by frame {dev.frame} "
                f"({dev.where}; tolerance {getattr(tol, name):g} on their running sum)")
            continue
        what = "the stored controls" if name in INPUT_FIELDS else (
            "the re-settled start" if dev.frame == 0 else f"where frame {dev.frame - 1} leads")
        worst = max(report.largest.get(name, dev), report.start.get(name, dev), key=lambda d: d.value)
        report.failures.append(
            f"{key}.{name}: {dev.value:.6g} from {what} at frame {dev.frame} ({dev.where}; tolerance "
            f"{tol.of(name, dev.frame):g}); largest {worst.value:.6g} at frame {worst.frame} ({worst.where})")


def _empty_record() -> ReplayRecord:
    return ReplayRecord(np.zeros((0, 7)), np.zeros((0, 6)), {}, {}, 0)


def stepwise_derivation(
    report: VerifyReport, derived: Derived, arrays: dict[str, np.ndarray], sequence_bytes: bytes,
    keyframes: dict[str, FloatArray], threads: int = 1,
) -> Derived:
    """Both replays checked stepwise against their stored states (``report.stepwise``, failures into
    ``report.failures``), and the result arrays and metrics made from the records at the stored states: what
    the stored arrays and figures are compared with. The restarts' figures stay ``derived``'s (their states are
    not stored). A replay whose states are missing or misshapen fails and keeps ``derived``'s record."""
    prep = derived.prep
    jobs = {"refined": keyframes, "raw": {side: sp.zero_keyframes() for side, sp in prep.spaces.items()}}

    presettle: FloatArray | None = None
    placed: Deviation | None = None
    if PRESETTLE_STATE_KEY in arrays:
        presettle, placed, problems = checked_presettle(prep, arrays[PRESETTLE_STATE_KEY])
        report.failures.extend(problems)
    else:
        report.config_notes.append(f"no stored pre-settle state ({PRESETTLE_STATE_KEY}: a result made before it was "
                                   "stored): frame 0 compared with a start settled afresh here")

    def run(name: str) -> tuple[StepwiseReport, ReplayRecord]:
        key = STATE_KEYS[name]
        if key not in arrays:
            return StepwiseReport(key, failures=[f"{key}: missing (the result stores the other replay's states)"]), \
                _empty_record()
        controls_key = CONTROL_KEYS[name]
        rep, rec = replay_stepwise(prep, jobs[name], arrays[key], key, controls=arrays.get(controls_key),
                                   controls_key=controls_key, presettle=presettle)
        rep.presettle = placed
        return rep, rec

    stored_without_inputs = [CONTROL_KEYS[n] for n in jobs if STATE_KEYS[n] in arrays and CONTROL_KEYS[n] not in arrays]
    if stored_without_inputs:
        report.config_notes.append(f"no stored inputs ({', '.join(stored_without_inputs)}: a result made before they "
                                   "were stored): stepped under the inputs the keyframes give here")
    names = list(jobs)
    if threads > 1:  # mj_step releases the GIL: the two replays side by side, the same records
        with ThreadPoolExecutor(max_workers=2, thread_name_prefix="stepwise") as pool:
            done = list(pool.map(run, names))
    else:
        done = [run(name) for name in names]
    records = {}
    for name, (rep, rec) in zip(names, done, strict=True):
        report.stepwise[name] = rep
        report.failures.extend(rep.failures)
        report.checked.append(rep.key)
        fallback = derived.final if name == "refined" else derived.raw
        records[name] = rec if len(rec.object_pose) == prep.num_frames else fallback
    final, raw = records["refined"], records["raw"]
    metrics = {"raw": replay_metrics(prep, raw), "refined": replay_metrics(prep, final)}
    out = build_arrays(prep, sequence_bytes, keyframes, final, raw, metrics["raw"], metrics["refined"])
    out.update({k: v for k, v in derived.arrays.items() if k.endswith("_attempt_keyframes")})
    return Derived(prep, raw, final, metrics, derived.attempt_metrics, out, derived.steps)
