"""Re-simulate a result to see it: the full simulation state per frame, raw replay and refined.

A result file stores the object trajectory, the hand keypoints and the controls, not the full MuJoCo state
(hinge angles, palm pose) that drawing the hand needs. ``resimulate`` rebuilds the scene exactly as
``hoi-refine verify`` does (``worker.refine.result.prepare_from_result``) and replays the stored keyframes
from frame 0 with ``worker.refine.run.replay`` — the same code that made the result — recording ``qpos`` at
every frame; the raw replay is the same replay with zero offsets, as ``refine_sequence`` made it. A raw-replay
result (``hoi-refine replay``, which does not embed its sequence: pass it) is that zero-offset replay of the
same scene. The stored trajectory's re-simulation is checked against the file (``compare_object_trajectory``, and
an articulated object's joint values too), so what is drawn is what the file holds. An articulated object starts at
its recorded frame-0 joint values, as in the product (``worker.simulation.stepping.initial_state``), and every part
is drawn where the simulation has it; ``Playback.part_poses_ref`` holds where the recording has each part.
"""

from __future__ import annotations

from collections.abc import Sequence as Seq
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from common.errors import ResultMismatchError, UnsupportedFormatError
from common.geometry import FloatArray
from common.result_format import read_arrays, read_summary
from common.sequence import Sequence

TRAJECTORIES: tuple[str, ...] = ("raw", "refined")


@dataclass
class Trajectory:
    """One simulated run, per frame (F frames)."""

    name: str  # "raw" or "refined"
    qpos: FloatArray  # (F, nq) the state at each frame time
    object_pose: FloatArray  # (F, 7) world x y z qw qx qy qz
    keypoints: dict[str, FloatArray]  # side -> (F, 21, 3)
    contacts: dict[str, np.ndarray]  # ``common.result_format.CONTACT_KEYS`` columns
    e_t_cm: FloatArray  # (F,) object position error
    e_r_deg: FloatArray  # (F,) object rotation error
    #: An articulated object's joint values (F, J) and per frame its largest joint error (deg, or cm for a
    #: prismatic joint: ``worker.simulation.metrics.ArticulationFrames``); None for a rigid object.
    articulation: FloatArray | None = None
    e_a: FloatArray | None = None


@dataclass
class Controls:
    """What the refined replay applied at each physics step (already interpolated between frames: hinge targets
    and wrist positions linearly, wrist rotations by slerp, see ``worker.simulation``), and the start state."""

    ctrl: FloatArray  # (S, nu) hinge servo targets
    mocap_pos: FloatArray  # (S, nmocap, 3)
    mocap_quat: FloatArray  # (S, nmocap, 4) wxyz
    start_physics: FloatArray  # mjSTATE_FULLPHYSICS state of frame 0 (the settled start)
    start_warmstart: FloatArray  # (nv,) qacc_warmstart of the start state
    eq_active: FloatArray  # (S, neq) which equality constraints are on: the wrist welds, the object's hold


@dataclass
class Playback:
    """A result rebuilt for viewing. ``scene``: ``worker.scene.Scene``; ``trajectories``: name -> Trajectory."""

    scene: Any
    sequence: Sequence
    summary: dict[str, Any]
    arrays: dict[str, np.ndarray]
    object_pose_ref: FloatArray  # (F, 7) the recorded object
    keypoints_ref: dict[str, FloatArray]  # side -> (F, 21, 3) the recorded hand
    #: (F, P, 7) every part's recorded world pose, base first (a rigid object: its pose, P = 1).
    part_poses_ref: FloatArray
    articulation_ref: FloatArray | None = None  # (F, J) the recorded joint values of an articulated object
    trajectories: dict[str, Trajectory] = field(default_factory=dict)
    controls: Controls | None = None  # of the refined replay (``export``)

    @property
    def fps(self) -> float:
        return float(self.scene.fps)

    @property
    def num_frames(self) -> int:
        return int(self.object_pose_ref.shape[0])

    @property
    def articulated(self) -> bool:
        return self.articulation_ref is not None

    def joint_labels(self) -> list[str]:
        """Each joint's name with the unit its error is shown in, e.g. ``lid_hinge (deg)``."""
        return [f"{j.name} ({j.unit})" for j in self.sequence.object.joints]


def load_result(path_or_blob: Any) -> bytes:
    """Result bytes from a path or bytes, with a clear error for a file that is not a result."""
    if isinstance(path_or_blob, bytes | bytearray):
        return bytes(path_or_blob)
    path = Path(path_or_blob)
    if path.is_dir():
        raise UnsupportedFormatError(f"{path}: is a folder, not a result file (give one result .npz)")
    if not path.is_file():
        raise UnsupportedFormatError(f"{path}: no such result file")
    return path.read_bytes()


def main_trajectory(summary: dict[str, Any]) -> str:
    """The trajectory a result file stores (``object_pose_sim``, contacts): refined, or raw for a raw replay."""
    return "raw" if summary.get("kind") == "replay" else "refined"


def _prepare(
    blob: bytes, summary: dict[str, Any], sequence: Sequence | None, cache_dir: Path | None, mano_dir: Path | None
) -> tuple[Any, dict[str, FloatArray]]:
    """The ``Prepared`` problem and the keyframes of the stored trajectory (zero offsets for a raw replay)."""
    from worker.refine.result import RESULT_KIND, prepare_from_result, sim_config_from_summary

    kind = summary.get("kind")
    if kind == RESULT_KIND:
        return prepare_from_result(blob, sequence, cache_dir=cache_dir, mano_dir=mano_dir)
    if kind != "replay":
        raise UnsupportedFormatError(f"not a refinement or raw-replay result (kind {kind!r})")
    if sequence is None:
        raise UnsupportedFormatError("a raw-replay result embeds no sequence; pass --sequence (the replayed file)")
    from common.job_options import JobOptions
    from worker.refine.prepare import prepare

    # The refinement's zero-offset replay is the raw replay (same controls, same start): checked below.
    # A robot hand's replay keeps its packed description (``hoi-refine replay --hand``).
    options = JobOptions.model_validate({"hand": summary["hand"]}) if summary.get("hand") else JobOptions()
    prep = prepare(sequence, options, sim_config_from_summary(summary["config"]), cache_dir=cache_dir,
                   mano_dir=mano_dir)  # fmt: skip
    return prep, {side: sp.zero_keyframes() for side, sp in prep.spaces.items()}


def resimulate(
    blob: bytes,
    sequence: Sequence | None = None,
    which: Seq[str] | None = None,
    record_controls: bool = False,
    *,
    cache_dir: Path | None = None,
    mano_dir: Path | None = None,
) -> Playback:
    """Rebuild a result's scene and re-simulate the trajectories named in ``which`` (default: all it has — raw
    and refined for a refinement, raw for a raw replay; see the module docstring). ``record_controls`` also keeps
    the stored trajectory's per-step controls (``Playback.controls``, for ``export``). ``sequence``: the input,
    when the result does not embed it (raw replays). ``cache_dir`` (convex parts) and ``mano_dir`` (MANO
    model): as for ``worker.refine.prepare.prepare``; the commands pass the configured folders."""
    from common.geometry import rotation_error_deg
    from worker.refine.evaluator import CONTROL_SPEC, ParallelEvaluator, control_columns
    from worker.refine.prepare import settled_start
    from worker.refine.replay import replay
    from worker.refine.result import compare_object_trajectory
    from worker.simulation.replay import articulation_frames

    summary = read_summary(blob)
    arrays = read_arrays(blob)
    main = main_trajectory(summary)
    available = TRAJECTORIES if main == "refined" else ("raw",)
    which = available if which is None else tuple(which)
    unknown = [w for w in which if w not in available]
    if unknown or not which:
        raise UnsupportedFormatError(f"this result has the trajectories {list(available)}, not {list(which)}")
    prep, keyframes = _prepare(blob, summary, sequence, cache_dir, mano_dir)
    ref_pose = prep.obj_targets_pose()
    seq = prep.seq
    out = Playback(
        scene=prep.scene,
        sequence=seq,
        summary=summary,
        arrays=arrays,
        object_pose_ref=ref_pose,
        keypoints_ref={r.side: r.keypoints for r in prep.references},
        part_poses_ref=seq.object.part_poses(ref_pose, seq.articulation),
        articulation_ref=None if not seq.object.parts else seq.articulation,
    )
    model = prep.scene.model
    s = prep.scene.substeps_per_frame
    n_frames = prep.num_frames
    with ParallelEvaluator(model, 1) as ev:
        start, _ = settled_start(prep, ev)
        for name in which:
            offsets = keyframes if name == "refined" else {k: sp.zero_keyframes() for k, sp in prep.spaces.items()}
            qpos = np.empty((n_frames, model.nq))
            start.restore(model, ev.step_data)
            qpos[0] = ev.step_data.qpos
            steps: list[FloatArray] = []
            keep_controls = record_controls and name == main

            def on_step(i: int, d: mujoco.MjData, qpos: FloatArray = qpos, steps: list[FloatArray] = steps,
                        keep: bool = keep_controls) -> None:
                # The state after step i is frame (i + 1) / s's state (``replay`` reads sensors at the same time).
                if (i + 1) % s == 0 and (i + 1) // s < n_frames:
                    qpos[(i + 1) // s] = d.qpos
                if keep:
                    c = np.empty(mujoco.mj_stateSize(model, CONTROL_SPEC))
                    mujoco.mj_getState(model, d, c, CONTROL_SPEC)
                    steps.append(c)

            rec = replay(prep, ev, start, offsets, record_contacts=True, on_step=on_step)
            if name == main:  # what is drawn is what the file holds
                compare_object_trajectory(arrays["object_pose_sim"], rec.object_pose)
                compare_articulation(arrays.get("object_articulation_sim"), rec.articulation)
            arti = articulation_frames(seq, rec.articulation)
            out.trajectories[name] = Trajectory(
                name=name,
                qpos=qpos,
                object_pose=rec.object_pose,
                keypoints=rec.keypoints,
                contacts=rec.contacts,
                e_t_cm=100.0 * np.linalg.norm(rec.object_pose[:, :3] - ref_pose[:, :3], axis=1),
                e_r_deg=np.asarray(rotation_error_deg(rec.object_pose[:, 3:], ref_pose[:, 3:])),
                articulation=rec.articulation,
                e_a=None if arti is None else arti.errors(n_frames)[0],
            )
            if keep_controls:
                packed = np.asarray(steps)
                cols, nm = control_columns(model), model.nmocap
                out.controls = Controls(
                    ctrl=packed[:, cols.ctrl].copy(),
                    mocap_pos=packed[:, cols.mocap_pos].reshape(-1, nm, 3).copy(),
                    mocap_quat=packed[:, cols.mocap_quat].reshape(-1, nm, 4).copy(),
                    start_physics=start.physics.copy(),
                    start_warmstart=start.warmstart.copy(),
                    eq_active=packed[:, cols.eq_active].copy(),
                )
    return out


#: How far (rad or m) a re-simulated joint value may be from the stored one: the object trajectory's own tolerance
#: (``worker.refine.result.VERIFY_TOLERANCE_M``) read in the joint's unit; a re-simulation on the same build matches
#: to the last bits.
ARTICULATION_TOLERANCE = 1e-6


def compare_articulation(stored: np.ndarray | None, simulated: FloatArray | None) -> None:
    """``ResultMismatchError`` when a result's stored joint values (F, J) and the re-simulation's differ (or one of
    them is missing)."""
    if stored is None and simulated is None:
        return
    if stored is None or simulated is None or stored.shape != simulated.shape:
        raise ResultMismatchError(f"object_articulation_sim has shape {getattr(stored, 'shape', None)}, the "
                                  f"re-simulation {getattr(simulated, 'shape', None)}")  # fmt: skip
    diff = np.abs(np.asarray(stored, dtype=np.float64) - simulated)
    if diff.size and diff.max() > ARTICULATION_TOLERANCE:
        frame, joint = np.unravel_index(int(np.argmax(diff)), diff.shape)
        raise ResultMismatchError(f"object articulation differs from the re-simulation: {diff.max():.3g} at frame "
                                  f"{frame}, joint {joint}")  # fmt: skip


def finger_of_body(body: str) -> str:
    """The finger a hand body belongs to (``right_index2`` -> ``index``), ``palm`` for the palm."""
    from worker.hand.model import FINGERS

    name = body.split("_", 1)[-1]
    for finger in FINGERS:
        if name.startswith(finger):
            return str(finger)
    return "palm"


def contact_force_per_finger(contacts: dict[str, np.ndarray], num_frames: int, side: str | None = None
                             ) -> dict[str, FloatArray]:
    """Summed contact force magnitude (N) per finger (and palm) per frame, of one hand (``side``) or of both."""
    from worker.hand.model import FINGERS

    out = {name: np.zeros(num_frames) for name in (*FINGERS, "palm")}
    frames = np.asarray(contacts["contact_frame"], dtype=np.int64)
    mags = np.linalg.norm(np.asarray(contacts["contact_force"], dtype=np.float64).reshape(-1, 3), axis=1)
    hands = contacts["contact_hand"] if side is not None else [None] * len(frames)
    for frame, body, mag, hand in zip(frames, contacts["contact_body"], mags, hands, strict=True):
        if 0 <= frame < num_frames and (side is None or str(hand) == side):
            out[finger_of_body(str(body))][frame] += mag
    return out
