"""Raw replay (DESIGN §1.8): drive the hand along the retargeted reference with no optimisation.

``raw_replay(seq)`` retargets every hand, builds the scene, simulates the object from its rest pose
(``rest_pose``) and returns trajectories, contacts, metrics and timings; ``replay_result_bytes`` writes
it in the ``common.result_format`` layout (summary: ``metrics.raw``, config, versions, timings, IK residual,
hand model), plus ``S_mano_*`` parameters of the driven pose for hands whose reference came from MANO. With
``hand`` (a packed robot hand description, issue #55) the recorded hand is retargeted to that robot
(``worker.robot.retarget``) and the summary keeps the description (``hand``), so render, view and export rebuild
the same scene. The
timings are all wall clock (``*_s``, ``steps_per_second``): the file stores them in ``timings_json``; the
deterministic step count is ``simulated_steps``.
"""

from __future__ import annotations

import importlib.metadata as md
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from common.cpu_kind import cpu_model, numpy_simd
from common.hand_description import HandDescription
from common.result_format import write_result_npz
from common.sequence import Sequence
from worker.hand.mano.pose import reference_mano_arrays
from worker.hand.retarget import retarget_sequence
from worker.simulation.metrics import ArticulationFrames, compute_metrics, scalar_metrics
from worker.simulation.scene import Scene, SimConfig, build_scene
from worker.simulation.stepping import (
    Controls,
    HandTargets,
    RolloutRecord,
    initial_state,
    rollout,
    substep_controls,
)


@dataclass
class ReplayResult:
    """Everything a raw replay produced. ``timings`` in seconds; ``steps`` counts settle + rollout steps."""

    sequence: str
    references: list[Any]  # HandReference, or RobotReference for a robot hand
    scene: Scene
    controls: Controls
    record: RolloutRecord
    object_pose_ref: np.ndarray
    metrics: dict[str, Any]
    timings: dict[str, float] = field(default_factory=dict)
    steps: int = 0
    mano_arrays: dict[str, np.ndarray] = field(default_factory=dict)  # S_mano_* of MANO hands
    articulation_ref: np.ndarray | None = None  # (F, J) recorded joint values of an articulated object
    hand: HandDescription | None = None  # the robot hand driven (None: the human hand)

    @property
    def contacts(self) -> dict[str, np.ndarray]:
        assert self.record.contacts is not None
        return self.record.contacts

    def ik_residual_mm(self) -> dict[str, float]:
        """Per side, the retargeting's mean keypoint residual (a robot's: its sites to the human keypoints)."""
        return {r.side: r.mean_residual_mm() for r in self.references}


def residual_mm(ref: Any) -> np.ndarray:
    """(T,) a reference's keypoint residual (mm): ``HandReference.residual_mm``, or a robot's sites to the human
    keypoints they follow (``RobotReference.residual_mm()``)."""
    return np.asarray(ref.residual_mm() if callable(ref.residual_mm) else ref.residual_mm)


def versions() -> dict[str, str]:
    """Package versions, and the CPU kind (model, NumPy's SIMD dispatch): with the same code, versions and CPU kind
    a refinement gives the same figures bit for bit; on another CPU kind some sequences differ
    (``common.cpu_kind``), which these let a reader tell apart from a change of code."""
    out = {"python": platform.python_version(), "mujoco": mujoco.__version__, "numpy": np.__version__,
           "scipy": _installed("scipy"), "cpu": cpu_model(), "numpy_simd": numpy_simd()}
    out["hoi-refine"] = _installed("hoi-refine")
    return out


def _installed(name: str) -> str:
    try:
        return md.version(name)
    except md.PackageNotFoundError:  # pragma: no cover - running from a source tree without install
        return "unknown"


def raw_replay(
    seq: Sequence,
    config: SimConfig | None = None,
    record_contacts: bool = True,
    *,
    cache_dir: Path | None = None,
    mano_dir: Path | None = None,
    hand: HandDescription | None = None,
) -> ReplayResult:
    """Retarget, build the scene and replay the reference open-loop; see the module docstring. ``cache_dir``:
    where convex parts are cached (None: memory only); ``mano_dir``: the MANO model folder (None: no MANO);
    ``hand``: a packed robot hand description to drive instead of the human hand."""
    config = config or SimConfig()
    t0 = time.perf_counter()
    references: list[Any] = list(retarget_sequence(seq, mano_dir=mano_dir))
    fingertips = None
    if hand is not None:
        from worker.robot.retarget import robot_references

        references = list(robot_references(references, hand, float(seq.fps)))
        fingertips = {r.side: tuple(r.embodiment.fingertips) for r in references}
    t1 = time.perf_counter()
    scene = build_scene(seq, references, config, cache_dir=cache_dir)
    data = scene.make_data()
    t2 = time.perf_counter()
    targets: dict[str, HandTargets] = {r.side: HandTargets.from_reference(r) for r in references}
    state0, settle_steps = initial_state(scene, data, targets, with_warmstart=True)
    controls = substep_controls(scene, targets)
    record = rollout(
        scene, data, state0, controls.ctrl, controls.mocap_pos, controls.mocap_quat, record_contacts=record_contacts
    )
    t3 = time.perf_counter()
    object_ref = seq.object_pose_world()
    metrics = compute_metrics(
        record.object_pose,
        object_ref,
        record.keypoints,
        {r.side: r.keypoints for r in references},
        {r.side: r.valid for r in references},
        record.contact_frames,
        articulation_frames(seq, record.articulation),
        fingertips,
    )
    steps = settle_steps + record.steps
    mano_arrays: dict[str, np.ndarray] = {}
    if any(r.from_mano for r in references):  # the driven pose as MANO parameters (DESIGN §1.7)
        mano_arrays = reference_mano_arrays(seq, references, mano_dir)
    timings = {
        "retarget_s": t1 - t0,
        "build_scene_s": t2 - t1,
        "simulate_s": t3 - t2,
        "total_s": time.perf_counter() - t0,
        "steps_per_second": steps / max(t3 - t2, 1e-9),
    }
    return ReplayResult(
        sequence=seq.name,
        references=references,
        scene=scene,
        controls=controls,
        record=record,
        object_pose_ref=object_ref,
        metrics=metrics,
        timings=timings,
        steps=steps,
        mano_arrays=mano_arrays,
        articulation_ref=seq.articulation,
        hand=hand,
    )


def articulation_frames(seq: Sequence, simulated: np.ndarray | None) -> ArticulationFrames | None:
    """The joint values a metric compares for an articulated object (None for a rigid one)."""
    if not seq.object.parts or simulated is None or seq.articulation is None:
        return None
    return ArticulationFrames(simulated, seq.articulation, tuple(j.kind for j in seq.object.joints))


def replay_summary(result: ReplayResult) -> dict[str, Any]:
    """The JSON summary stored in the result file."""
    cfg = result.scene.config.to_dict()
    robot = result.hand is not None
    summary = {
        "kind": "replay",
        "sequence": result.sequence,
        "fps": result.scene.fps,
        "frames": int(result.record.object_pose.shape[0]),
        "metrics": {"raw": scalar_metrics(result.metrics)},
        "config": {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()},
        "versions": versions(),
        "timings": result.timings,
        "simulated_steps": result.steps,
        "ik_residual_mm": result.ik_residual_mm(),
        "hand_length_m": {} if robot else {r.side: r.geometry.hand_length for r in result.references},
        "hand_model": {r.side: result.hand.name if result.hand is not None else "MANO" if r.from_mano else "built-in"
                       for r in result.references},
        "object_collision": result.scene.object_collision,
        "table": result.scene.table.to_dict(),
        "object_hold": result.scene.hold_summary(),
        "num_contacts": len(result.contacts["contact_frame"]),
    }
    if result.hand is not None:  # the packed description: render / view / export rebuild the robot's scene
        summary["hand"] = result.hand.model_dump(mode="json")
    return summary


def replay_arrays(result: ReplayResult) -> dict[str, np.ndarray]:
    """The result-file arrays of a replay (``common.result_format`` keys)."""
    rec = result.record
    arrays: dict[str, np.ndarray] = {
        "object_pose_sim": rec.object_pose,
        "object_vel_sim": rec.object_vel,
        "object_pose_ref": result.object_pose_ref,
    }
    for ref in result.references:
        s = ref.side
        arrays[f"{s}_q_target"] = ref.q
        arrays[f"{s}_wrist_pos"] = ref.wrist_pos
        arrays[f"{s}_wrist_quat"] = ref.wrist_quat
        arrays[f"{s}_keypoints_sim"] = rec.keypoints[s]
        arrays[f"{s}_keypoints_ref"] = ref.keypoints
        arrays[f"{s}_valid"] = ref.valid
        arrays[f"{s}_ik_residual_mm"] = residual_mm(ref)
    if rec.articulation is not None and result.articulation_ref is not None:
        arrays["object_articulation_sim"] = rec.articulation
        arrays["object_articulation_ref"] = result.articulation_ref
    for key, val in result.metrics["per_frame"].items():
        arrays[f"metrics_raw_{key}"] = val
    arrays.update(result.contacts)
    arrays.update(result.mano_arrays)
    return arrays


def replay_result_bytes(result: ReplayResult, wall_clock: bool = True) -> bytes:
    """Serialise a replay with ``common.result_format.write_result_npz`` (``wall_clock=False``: no timings)."""
    return write_result_npz(replay_arrays(result), replay_summary(result), wall_clock=wall_clock)
