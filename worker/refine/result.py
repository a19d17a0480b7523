"""The refinement result file (issue #3 item 5); ``verify`` lives in ``worker.refine.verify``.

Arrays (``common.result_format`` keys plus; all but the loss history made by ``worker.refine.derive``):
``object_pose_ref`` (F,7); per side ``S_keyframes`` (N, 13|16) the optimised offsets,
``S_attempt_keyframes`` (A, N, 13|16) every attempt's when there were restarts,
``S_q_target``/``S_wrist_pos``/``S_wrist_quat`` the per-frame controls they give,
``S_keypoints_sim``/``S_keypoints_ref``/``S_valid``; ``raw_object_pose_sim`` (F,7) the raw replay;
``object_table_contact`` (F,) bool, the refined object touching the table;
``metrics_{raw,refined}_*`` per-frame errors, penetration (mm) and hand-only hold (``worker.metrics``);
``window_loss_history`` (W, G) best loss per generation (NaN
padded); ``sequence_npz`` (uint8) the input sequence in the native NPZ format, so ``verify`` needs nothing
else. Summary JSON: kind, sequence, fps, frames, metrics.raw / metrics.refined (both
protocols, plausibility, first-attempt success; ``worker.metrics``), options, config (simulation
settings, keyframe interval, CMA-ES settings, loss weights), seed, versions, table (the plane under the frame-0
object: point, normal, tilt_deg), attempts (seed, success, E_t, E_r, evaluations of each CMA-ES run; the
result is the best), windows (count, skipped, escalated, per window loss), timings (the
deterministic counters; the wall-clock figures are stored in the ``timings_json`` member, see
``common.result_format``, and ``read_summary`` merges them back).
"""

from __future__ import annotations

from dataclasses import asdict
from typing import TYPE_CHECKING, Any

from common.sequence import Sequence
from worker.refine.windowed import CmaSettings, WindowLog

if TYPE_CHECKING:
    from worker.refine.prepare import Prepared

RESULT_KIND = "refine"


def versions() -> dict[str, str]:
    """The raw replay's package versions plus the optimiser's."""
    import cma

    from worker.replay import versions as replay_versions

    return {**replay_versions(), "cma": str(cma.__version__).split()[0]}


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


def verify_result(blob: bytes, sequence: Sequence | None = None, allow_config: bool = False) -> dict[str, Any]:
    """``worker.refine.verify.verify_result`` (kept here for callers of the earlier API)."""
    from worker.refine.verify import verify_result as verify

    return verify(blob, sequence, allow_config)
