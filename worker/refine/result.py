"""The refinement result file (issue #3 item 5); ``verify`` lives in ``worker.verification``.

Arrays (``common.result_format`` keys plus; all but the loss history made by ``worker.refine.derive``):
``object_pose_ref`` (F,7); per side ``S_keyframes`` (N, 13|16) the optimised offsets,
``S_attempt_keyframes`` (A, N, 13|16) every attempt's when there were several (restarts, the polish),
``S_q_target``/``S_wrist_pos``/``S_wrist_quat`` the per-frame controls they give,
``S_keypoints_sim``/``S_keypoints_ref``/``S_valid``; ``raw_object_pose_sim`` (F,7) the raw replay;
``object_table_contact`` (F,) bool, the refined object touching the table; ``state_sim`` / ``raw_state_sim`` (F, S)
each replay's integration state per frame (``worker.refine.replay.INTEGRATION_STATE``, for ``verify``'s stepwise
check) and ``control_sim`` / ``raw_control_sim`` (T, C) its inputs per physics step, which that check steps under;
``metrics_{raw,refined}_*`` per-frame errors, penetration (mm) and hand-only hold (``worker.simulation.metrics``);
``window_loss_history`` (W, G) best loss per generation (NaN padded); ``sequence_npz`` (uint8) the input
sequence in the native NPZ format, so ``verify`` needs nothing else. Summary JSON: kind, sequence, fps, frames,
outcome (executable on the paper's protocol and why not: ``common.outcome``, ``worker.refine.outcome``),
metrics.raw / metrics.refined (both protocols, plausibility, first-attempt success), options, config (simulation
settings, keyframe interval, CMA-ES settings, loss weights), seed, versions, table (the plane under the frame-0
object: point, normal, tilt_deg), attempts (seed, lookahead rotation factor, polish, success, E_t, E_r on both
protocols, evaluations of each CMA-ES run; the result is the best), windows (count, skipped, escalated, stopped
early, per window loss), timings (the deterministic counters; the wall-clock figures are stored in the
``timings_json`` member, see ``common.result_format``, and ``read_summary`` merges them back).
``prepare_from_result`` and ``compare_object_trajectory`` serve the visual tools' replays.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import ResultMismatchError, UnsupportedFormatError
from common.geometry import FloatArray
from common.job_options import JobOptions
from common.result_format import read_arrays, read_summary
from common.sequence import Sequence
from common.sequence_io import sequence_from_npz_bytes
from worker.refine.environment import versions
from worker.refine.prepare import ROBOT_JOINT_SPEED, Prepared, prepare
from worker.refine.windowed import CmaSettings, WindowLog
from worker.simulation.config import OLDER_SIM_DEFAULTS, SimConfig
from worker.simulation.table_fit import TableChoice

RESULT_KIND = "refine"
#: The visual tools' tolerance on a re-simulated object trajectory (m): on the same build it reproduces bit for
#: bit (``verify`` has its own, cross-host tolerances: ``worker.verification.report``).
VERIFY_TOLERANCE_M = 1e-6


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
    lookahead_rotation_weight: float | None = None,
    outcome: dict[str, Any] | None = None,
) -> dict[str, Any]:
    cfg = prep.scene.config.to_dict()
    return {
        "kind": RESULT_KIND,
        "sequence": prep.seq.name,
        "fps": float(prep.seq.fps),
        "frames": int(prep.num_frames),
        "sides": list(prep.spaces),
        # Executable on the paper's protocol, and why not (``common.outcome``, ``worker.refine.outcome``).
        **({} if outcome is None else {"outcome": outcome}),
        "metrics": {"raw": m_raw, "refined": m_ref},
        "options": prep.options.model_dump(mode="json"),
        "seed": int(settings.seed),
        "config": {
            "sim": {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()},
            "keyframe_interval": int(prep.interval),
            "keyframes": int(prep.spaces[next(iter(prep.spaces))].n_keyframes),
            # JSON has no infinity (PostgreSQL's json type and strict clients refuse it): an unbounded level,
            # as a polish sweep's escalation, is null, "never".
            "cma": {k: None if isinstance(v, float) and not math.isfinite(v) else v
                    for k, v in asdict(settings).items()},
            "loss_weights": weights,
            # The kept attempt's factor on the object's rotation error over a window's lookahead frames
            # (``worker.refine.run.attempt_plan``); absent from results made before it existed (1).
            "lookahead_rotation_weight": lookahead_rotation_weight,
            "free_wrist_translation": bool(prep.options.free_wrist_translation),
            "rotation_pivot": prep.rotation_pivot,
            # "mirrored": a left hand's coordinates mirror a right hand's (``prepare.prepare(mirror_left=...)``);
            # results without this key were made with the right hand's coordinates for both sides.
            "left_hand_controls": "mirrored" if prep.mirror_left else "as right",
            # A robot hand's: "within limits", its retargeted motion brought within its joint speed limits
            # (``prepare.prepare(robot_speed_limits=...)``); robot results without this key were made without.
            **({"robot_joint_speed": ROBOT_JOINT_SPEED[prep.robot_speed_limits]}
               if prep.options.hand is not None else {}),
            "pose_basis": prep.basis_provenance,
        },
        "versions": versions(),
        "windows": {
            "count": len(logs),
            "skipped": int(sum(w.skipped for w in logs)),
            "optimised": int(sum(not w.skipped for w in logs)),
            "escalated": int(sum(w.escalated for w in logs)),
            "stopped_early": int(sum(w.stopped_early for w in logs)),
            # Windows a first pass ran again with the ones before them (``windowed``; only where rewinds were on).
            **({"rewound": int(sum(w.rewound for w in logs))} if settings.rewind_windows > 0 else {}),
            "per_window": [
                {"keyframe": w.index, "skipped": w.skipped, "touched": w.touched, "escalated": w.escalated,
                 "stopped_early": w.stopped_early, "initial_loss": w.initial_loss, "best_loss": w.best_loss,
                 "evaluations": w.evaluations}
                for w in logs
            ],
        },
        "table": prep.scene.table_summary(),
        "object_hold": prep.scene.hold_summary(),
        "attempts": attempts or [],
        "num_contacts": int(num_contacts),
        "timings": timings,
    }


def sim_config_from_summary(stored: dict[str, Any]) -> SimConfig:
    """The ``SimConfig`` a result was simulated with, from its summary's JSON form (``OLDER_SIM_DEFAULTS`` for
    the settings it predates)."""
    sim: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in stored.items()}
    return SimConfig(**{**OLDER_SIM_DEFAULTS, **sim})


def prepare_from_result(
    blob: bytes, sequence: Sequence | None = None, *, cache_dir: Path | None = None, mano_dir: Path | None = None
) -> tuple[Prepared, dict[str, FloatArray]]:
    """Rebuild a refinement result's problem (same sequence, options and simulation settings as the run) and its
    stored keyframes per hand side, checked against the stored per-frame controls (``cache_dir`` and
    ``mano_dir`` as for ``prepare``). Shared by ``verify_result`` and the visual tools (``worker.visual``)."""
    summary = read_summary(blob)
    if summary.get("kind") != RESULT_KIND:
        raise UnsupportedFormatError(f"not a refinement result (kind {summary.get('kind')!r})")
    arrays = read_arrays(blob)
    if sequence is None:
        if "sequence_npz" not in arrays:
            raise UnsupportedFormatError("the result embeds no sequence; pass --sequence")
        sequence = sequence_from_npz_bytes(arrays["sequence_npz"].tobytes())
    options = JobOptions.model_validate(summary["options"])
    prep = prepare(sequence, options, sim_config_from_summary(summary["config"]["sim"]),
                   rotation_pivot=summary["config"].get("rotation_pivot", "wrist"), cache_dir=cache_dir,
                   mano_dir=mano_dir, mirror_left=summary["config"].get("left_hand_controls") == "mirrored",
                   robot_speed_limits=summary["config"].get("robot_joint_speed") == ROBOT_JOINT_SPEED[True],
                   table=TableChoice.from_summary(summary.get("table") or {}))  # fmt: skip
    keyframes = {}
    for side, space in prep.spaces.items():
        key = f"{side}_keyframes"
        if key not in arrays or arrays[key].shape != (space.n_keyframes, space.dim):
            raise ResultMismatchError(f"{key}: missing or not ({space.n_keyframes}, {space.dim}) for this sequence")
        keyframes[side] = arrays[key]
        q, _, _ = space.frame_controls(arrays[key])
        if not np.allclose(q, arrays[f"{side}_q_target"], atol=1e-9):
            raise ResultMismatchError(f"{side}_q_target does not match the stored keyframes")
    return prep, keyframes


def compare_object_trajectory(stored: FloatArray, simulated: FloatArray) -> float:
    """The largest position difference (m) between two (F, 7) object trajectories; ``ResultMismatchError``
    when they differ beyond ``VERIFY_TOLERANCE_M`` (or in rotation beyond rounding)."""
    if stored.shape != simulated.shape:
        raise ResultMismatchError(f"object_pose_sim has shape {stored.shape}, re-simulation {simulated.shape}")
    diff = np.linalg.norm(stored[:, :3] - simulated[:, :3], axis=1)
    qdiff = np.abs(np.abs(np.sum(stored[:, 3:] * simulated[:, 3:], axis=1)) - 1.0)
    worst = int(np.argmax(diff))
    if diff[worst] > VERIFY_TOLERANCE_M or qdiff.max() > 1e-9:
        raise ResultMismatchError(
            f"object trajectory differs from the re-simulation: {diff[worst] * 1000:.3f} mm at frame {worst} "
            f"({int((diff > VERIFY_TOLERANCE_M).sum())} of {len(diff)} frames beyond {VERIFY_TOLERANCE_M} m)"
        )
    return float(diff.max())


def verify_result(
    blob: bytes, sequence: Sequence | None = None, *, allow_config: bool = False, cache_dir: Path | None = None,
    mano_dir: Path | None = None,
) -> dict[str, Any]:
    """``worker.verification.verify_result``: recompute everything the result claims (kept here for callers of the
    earlier API)."""
    from worker.verification import verify_result as verify

    return verify(blob, sequence, allow_config=allow_config, cache_dir=cache_dir, mano_dir=mano_dir)
