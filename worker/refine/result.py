"""The refinement result file (issue #3 item 5) and ``verify`` (item 6).

Arrays (``common.result_format`` keys plus): ``object_pose_ref`` (F,7); per side ``S_keyframes`` (N, 13|16)
the optimised offsets, ``S_q_target``/``S_wrist_pos``/``S_wrist_quat`` the per-frame controls they give,
``S_keypoints_sim``/``S_keypoints_ref``/``S_valid``; ``raw_object_pose_sim`` (F,7) the raw replay;
``metrics_{raw,refined}_*`` per-frame errors; ``window_loss_history`` (W, G) best loss per generation (NaN
padded); ``sequence_npz`` (uint8) the input sequence in the native NPZ format, so ``verify`` needs nothing
else. Summary JSON: kind, sequence, fps, frames, metrics.raw / metrics.refined, options, config (simulation
settings, keyframe interval, CMA-ES settings, loss weights), seed, versions, table (the plane under the frame-0
object: point, normal, tilt_deg), attempts (seed, success, E_t, E_r, evaluations of each CMA-ES run; the
result is the best), windows (count, skipped, escalated, per window loss), timings (the
deterministic counters; the wall-clock figures are stored in the ``timings_json`` member, see
``common.result_format``, and ``read_summary`` merges them back).
"""

from __future__ import annotations

from dataclasses import asdict
from typing import TYPE_CHECKING, Any

import numpy as np

from common.errors import ResultMismatchError, UnsupportedFormatError
from common.job_options import JobOptions
from common.result_format import read_arrays, read_summary
from common.sequence import Sequence
from common.sequence_io import sequence_from_npz_bytes, sequence_to_npz_bytes
from worker.refine.spline import FloatArray
from worker.refine.windowed import CmaSettings, WindowLog

if TYPE_CHECKING:
    from worker.refine.prepare import Prepared
    from worker.refine.run import ReplayRecord

RESULT_KIND = "refine"
#: verify tolerance on object positions (m): a re-simulation on the same build reproduces bit for bit; the
#: margin only absorbs libm differences between machines.
VERIFY_TOLERANCE_M = 1e-6


def versions() -> dict[str, str]:
    """The raw replay's package versions plus the optimiser's."""
    import cma

    from worker.replay import versions as replay_versions

    return {**replay_versions(), "cma": str(cma.__version__).split()[0]}


def build_arrays(
    prep: Prepared,
    keyframes: dict[str, FloatArray],
    final: ReplayRecord,
    raw: ReplayRecord,
    m_raw: dict[str, Any],
    m_ref: dict[str, Any],
    logs: list[WindowLog] | None = None,
) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {
        "object_pose_sim": final.object_pose,
        "object_vel_sim": final.object_vel,
        "object_pose_ref": prep.obj_targets_pose(),
        "raw_object_pose_sim": raw.object_pose,
        "sequence_npz": np.frombuffer(sequence_to_npz_bytes(prep.seq), dtype=np.uint8),
    }
    for ref in prep.references:
        s = ref.side
        q, p, r = prep.spaces[s].frame_controls(keyframes[s])
        arrays[f"{s}_keyframes"] = keyframes[s]
        arrays[f"{s}_q_target"] = q
        arrays[f"{s}_wrist_pos"] = p
        arrays[f"{s}_wrist_quat"] = r
        arrays[f"{s}_keypoints_sim"] = final.keypoints[s]
        arrays[f"{s}_keypoints_ref"] = ref.keypoints
        arrays[f"{s}_valid"] = ref.valid
        if getattr(ref, "from_mano", False):
            # The refined hand as MANO parameters (issue #6): exact because the scene used the MANO geometry.
            from worker.mano.pose import mano_result_arrays

            hand = prep.seq.hand(s)
            assert hand is not None
            arrays.update(mano_result_arrays(prep.seq, hand, p, r, q))
    for name, m in (("raw", m_raw), ("refined", m_ref)):
        for key, val in m["per_frame"].items():
            arrays[f"metrics_{name}_{key}"] = val
    if logs is not None:
        width = max([len(w.history) for w in logs] + [1])
        hist = np.full((len(logs), width), np.nan)
        for i, w in enumerate(logs):
            hist[i, : len(w.history)] = w.history
        arrays["window_loss_history"] = hist
    arrays.update(final.contacts)
    return arrays


def build_summary(
    prep: Prepared,
    settings: CmaSettings,
    weights: dict[str, float],
    logs: list[WindowLog],
    m_raw: dict[str, Any],
    m_ref: dict[str, Any],
    timings: dict[str, Any],
    num_contacts: int = 0,
    attempts: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    cfg = prep.scene.config.to_dict()
    return {
        "kind": RESULT_KIND,
        "sequence": prep.seq.name,
        "fps": float(prep.seq.fps),
        "frames": int(prep.num_frames),
        "sides": list(prep.spaces),
        "metrics": {"raw": m_raw, "refined": m_ref},
        "options": prep.options.model_dump(mode="json"),
        "seed": int(settings.seed),
        "config": {
            "sim": {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()},
            "keyframe_interval": int(prep.interval),
            "keyframes": int(prep.spaces[next(iter(prep.spaces))].n_keyframes),
            "cma": asdict(settings),
            "loss_weights": weights,
            "free_wrist_translation": bool(prep.options.free_wrist_translation),
            "rotation_pivot": prep.rotation_pivot,
            # "mirrored": a left hand's coordinates mirror a right hand's (``prepare.prepare(mirror_left=...)``);
            # results without this key were made with the right hand's coordinates for both sides.
            "left_hand_controls": "mirrored" if prep.mirror_left else "as right",
            "pose_basis": prep.basis_provenance,
        },
        "versions": versions(),
        "windows": {
            "count": len(logs),
            "skipped": int(sum(w.skipped for w in logs)),
            "optimised": int(sum(not w.skipped for w in logs)),
            "escalated": int(sum(w.escalated for w in logs)),
            "per_window": [
                {"keyframe": w.index, "skipped": w.skipped, "touched": w.touched, "escalated": w.escalated,
                 "initial_loss": w.initial_loss, "best_loss": w.best_loss, "evaluations": w.evaluations}
                for w in logs
            ],
        },
        "table": prep.scene.table.to_dict(),
        "attempts": attempts or [],
        "num_contacts": int(num_contacts),
        "timings": timings,
    }


def verify_result(blob: bytes, sequence: Sequence | None = None) -> dict[str, Any]:
    """Re-simulate a result's stored keyframes from frame 0 and compare the object trajectory.

    Raises ``ResultMismatchError`` when the object trajectory (or the stored per-frame controls) differ.
    """
    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.prepare import initial_state, prepare
    from worker.refine.run import replay

    summary = read_summary(blob)
    if summary.get("kind") != RESULT_KIND:
        raise UnsupportedFormatError(f"not a refinement result (kind {summary.get('kind')!r})")
    arrays = read_arrays(blob)
    if sequence is None:
        if "sequence_npz" not in arrays:
            raise UnsupportedFormatError("the result embeds no sequence; pass --sequence")
        sequence = sequence_from_npz_bytes(arrays["sequence_npz"].tobytes())
    options = JobOptions.model_validate(summary["options"])
    from worker.scene import SimConfig

    sim: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in summary["config"]["sim"].items()}
    # Results made before the pivot was recorded turned the hand about the wrist; before the wrist lead was
    # recorded, the mocap followed the wrist track itself; before the rest pose, the object started from frame 0.
    sim.setdefault("wrist_lead_s", 0.0)
    sim.setdefault("rest_approach_m", 0.0)
    sim.setdefault("finger_lead_s", 0.0)
    prep = prepare(sequence, options, SimConfig(**sim), rotation_pivot=summary["config"].get("rotation_pivot", "wrist"),
                   mirror_left=summary["config"].get("left_hand_controls") == "mirrored")
    keyframes = {}
    for side, space in prep.spaces.items():
        key = f"{side}_keyframes"
        if key not in arrays or arrays[key].shape != (space.n_keyframes, space.dim):
            raise ResultMismatchError(f"{key}: missing or not ({space.n_keyframes}, {space.dim}) for this sequence")
        keyframes[side] = arrays[key]
        q, _, _ = space.frame_controls(arrays[key])
        if not np.allclose(q, arrays[f"{side}_q_target"], atol=1e-9):
            raise ResultMismatchError(f"{side}_q_target does not match the stored keyframes")
    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, _ = initial_state(prep, ev)
        rec = replay(prep, ev, start, keyframes, record_contacts=False)
    stored = arrays["object_pose_sim"]
    if stored.shape != rec.object_pose.shape:
        raise ResultMismatchError(f"object_pose_sim has shape {stored.shape}, re-simulation {rec.object_pose.shape}")
    diff = np.linalg.norm(stored[:, :3] - rec.object_pose[:, :3], axis=1)
    qdiff = np.abs(np.abs(np.sum(stored[:, 3:] * rec.object_pose[:, 3:], axis=1)) - 1.0)
    worst = int(np.argmax(diff))
    if diff[worst] > VERIFY_TOLERANCE_M or qdiff.max() > 1e-9:
        raise ResultMismatchError(
            f"object trajectory differs from the re-simulation: {diff[worst] * 1000:.3f} mm at frame {worst} "
            f"({int((diff > VERIFY_TOLERANCE_M).sum())} of {len(diff)} frames beyond {VERIFY_TOLERANCE_M} m)"
        )
    return {"frames": len(diff), "max_pos_diff_m": float(diff.max())}
