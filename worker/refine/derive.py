"""Everything a refinement result holds that follows from its inputs: one function for the worker and ``verify``.

``derive_result(sequence_bytes, options, config, pivot, keyframes)`` loads the sequence from the very bytes the
result embeds, prepares it (retargeting, scene, control spaces) in a fresh model, settles frame 0 in a fresh
``MjData``, and replays from frame 0 the raw reference (zero offsets) and the given keyframes (and each restart's
keyframes), recording contacts; then it computes the metrics of both replays and every derived result array.
``refine_sequence`` stores exactly what this returns for its best keyframes (handing over its own retargeting of
the same bytes, the one step it does not repeat), and ``verify`` calls it again on what the file holds, so an
honest result reproduces bit for bit on the same build (issue #15 item 1: the stored replay used to run on the
refinement's own sequence object while ``verify`` read the embedded copy, which had been normalised once more on
load; 1e-16 there grew to 0.066 mm in the contact-rich replay).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from common.geometry import FloatArray
from common.job_options import JobOptions
from common.result_format import INTEGRATION_CONTROL_KEYS, INTEGRATION_STATE_KEYS, PRESETTLE_STATE_KEY
from common.sequence_io import sequence_from_npz_bytes
from worker.hand.mano.pose import mano_result_arrays
from worker.hand.reference import HandReference
from worker.refine.evaluator import ParallelEvaluator
from worker.refine.prepare import Prepared, prepare, presettle_state, settled_start
from worker.refine.replay import ReplayJob, ReplayRecord, replay_all
from worker.robot.metrics import robot_motion_metrics
from worker.robot.reference import RobotReference
from worker.simulation.config import SimConfig
from worker.simulation.metrics import compute_metrics, scalar_metrics
from worker.simulation.replay import articulation_frames
from worker.simulation.table_fit import TableChoice

#: The result arrays holding each replay's integration state per frame (``worker.refine.replay.INTEGRATION_STATE``).
STATE_KEYS = dict(zip(("refined", "raw"), INTEGRATION_STATE_KEYS, strict=True))
#: The result arrays holding each replay's inputs per physics step (``ReplayRecord.controls``).
CONTROL_KEYS = dict(zip(("refined", "raw"), INTEGRATION_CONTROL_KEYS, strict=True))


@dataclass
class Derived:
    """What ``derive_result`` recomputed. ``metrics`` (raw / refined) are ``worker.simulation.metrics.compute_metrics``
    outputs (with per-frame arrays); ``attempt_metrics`` one per restart's keyframes (scalars only)."""

    prep: Prepared
    raw: ReplayRecord
    final: ReplayRecord
    metrics: dict[str, dict[str, Any]]
    attempt_metrics: list[dict[str, Any]]
    arrays: dict[str, np.ndarray]
    steps: int  # settle + replay physics steps


def derive_result(
    sequence_bytes: bytes,
    options: JobOptions,
    config: SimConfig,
    rotation_pivot: str,
    keyframes: dict[str, FloatArray],
    attempt_keyframes: list[dict[str, FloatArray]] | None = None,
    *,
    cache_dir: Path | None = None,
    mano_dir: Path | None = None,
    mirror_left: bool | None = None,
    references: list[HandReference] | None = None,
    threads: int = 1,
    attempt_details: list[str] | None = None,
    robot_speed_limits: bool = True,
    table: TableChoice | None = None,
) -> Derived:
    """See the module docstring. ``attempt_keyframes`` the keyframes of every attempt (restarts) in order, stored
    so ``verify`` can check the first attempt's success too; ``attempt_details`` the convex parts each ran on
    (``SimConfig.convex_detail``; None: all on ``config``'s): an attempt made on other parts than the result
    (``worker.refine.run.RESCUE``) is replayed on a preparation with those. ``cache_dir``, ``mano_dir`` and
    ``mirror_left`` (the
    left hand's control convention, ``config.left_hand_controls``) as for ``prepare``. ``references``: the
    retargeting of these very bytes, when the caller made it already (``refine_sequence``; ``verify`` never passes
    it, so a retargeting that did not reproduce would fail there). ``threads``: replays run side by side
    (``replay_all``; the same records whatever the number). ``robot_speed_limits`` as for ``prepare``
    (``config.robot_joint_speed``). ``table``: the result's stored table choice
    (``verify``: the scene stands on it; ``Prepared.scene.table_fit.choice_problems`` say whether the fit makes it
    here); attempts on other convex parts are prepared on the fit's own choice, as the refinement did."""
    seq = sequence_from_npz_bytes(sequence_bytes)
    prep = prepare(seq, options, config, rotation_pivot=rotation_pivot, cache_dir=cache_dir, mano_dir=mano_dir,
                   mirror_left=mirror_left, references=references, robot_speed_limits=robot_speed_limits,
                   table=table)
    for side, space in prep.spaces.items():
        k = keyframes.get(side)
        if k is None or k.shape != (space.n_keyframes, space.dim):
            got = None if k is None else k.shape
            raise ValueError(f"{side}_keyframes must have shape ({space.n_keyframes}, {space.dim}), got {got}")
    attempts = attempt_keyframes or []
    details = attempt_details or [config.convex_detail] * len(attempts)
    if len(details) != len(attempts):
        raise ValueError(f"{len(attempts)} attempts' keyframes but {len(details)} attempts' convex parts")
    own = [k for k, d in zip(attempts, details, strict=True) if d == config.convex_detail]
    zero = {side: sp.zero_keyframes() for side, sp in prep.spaces.items()}
    jobs = [ReplayJob(zero, record_states=True), ReplayJob(keyframes, record_states=True), *_attempt_jobs(own)]
    (raw, final, *tried), steps = _replays(prep, jobs, threads)
    attempt_metrics: list[dict[str, Any] | None] = [None] * len(attempts)
    for detail in dict.fromkeys(details):
        mine = [i for i, d in enumerate(details) if d == detail]
        on, records = prep, tried
        if detail != config.convex_detail:  # a rescued result's attempts on the product's parts, or the other way
            on = prepare(seq, options, replace(config, convex_detail=detail), rotation_pivot=rotation_pivot,
                         cache_dir=cache_dir, mano_dir=mano_dir, mirror_left=mirror_left, references=prep.references,
                         robot_speed_limits=robot_speed_limits)
            records, more = _replays(on, _attempt_jobs([attempts[i] for i in mine]), threads)
            steps += more
        for i, rec in zip(mine, records, strict=True):
            attempt_metrics[i] = scalar_metrics(replay_metrics(on, rec))
    metrics = {"raw": replay_metrics(prep, raw), "refined": replay_metrics(prep, final)}
    arrays = build_arrays(prep, sequence_bytes, keyframes, final, raw, metrics["raw"], metrics["refined"])
    for side in prep.spaces:
        if attempts:
            arrays[f"{side}_attempt_keyframes"] = np.stack([k[side] for k in attempts])
    return Derived(prep, raw, final, metrics, [m for m in attempt_metrics if m is not None], arrays, steps)


def _attempt_jobs(keyframes: list[dict[str, FloatArray]]) -> list[ReplayJob]:
    return [ReplayJob(k, record_contacts=False) for k in keyframes]


def _replays(prep: Prepared, jobs: list[ReplayJob], threads: int) -> tuple[list[ReplayRecord], int]:
    """``jobs`` replayed from ``prep``'s settled frame 0, and the physics steps (settle + replays). A fresh MjData
    (Python-stepped): nothing simulated before can leak into the result."""
    with ParallelEvaluator(prep.scene.model, 1) as ev:
        start, settle = settled_start(prep, ev)
    records, replay_steps = replay_all(prep, start, jobs, threads)
    return list(records), settle + replay_steps


def replay_metrics(prep: Prepared, rec: ReplayRecord) -> dict[str, Any]:
    """``compute_metrics`` of a replay against the prepared references (with plausibility when it has contacts);
    a robot hand's also carry ``robot``: per side, the margins and smoothness of ``worker.robot.metrics``."""
    m = compute_metrics(
        rec.object_pose,
        prep.obj_targets_pose(),
        rec.keypoints,
        {r.side: r.keypoints for r in prep.references},
        {r.side: r.valid for r in prep.references},
        rec.contact_frames,
        articulation_frames(prep.seq, rec.articulation),
        {side: tuple(t.fingertips) for side, t in prep.hand_targets.items()},
    )
    if rec.joints:
        m["robot"] = {}
        for r in prep.references:
            assert isinstance(r, RobotReference)
            emb = r.embodiment
            m["robot"][r.side] = robot_motion_metrics(
                rec.joints[r.side], rec.command[r.side], rec.joint_force[r.side], emb.q_limits,
                emb.velocity_limits, emb.effort_limits, float(prep.seq.fps))
    return m


def build_arrays(
    prep: Prepared,
    sequence_bytes: bytes,
    keyframes: dict[str, FloatArray],
    final: ReplayRecord,
    raw: ReplayRecord,
    m_raw: dict[str, Any],
    m_ref: dict[str, Any],
) -> dict[str, np.ndarray]:
    """The result arrays that follow from the inputs (``worker.refine.result`` lists them); the sequence is
    embedded as the very bytes it was loaded from."""
    arrays: dict[str, np.ndarray] = {
        "object_pose_sim": final.object_pose,
        "object_vel_sim": final.object_vel,
        "object_pose_ref": prep.obj_targets_pose(),
        "raw_object_pose_sim": raw.object_pose,
        "sequence_npz": np.frombuffer(sequence_bytes, dtype=np.uint8).copy(),
    }
    # Every frame's integration state and every step's inputs, so ``verify`` can check each frame against the one
    # before it on any host (``worker.verification.stepwise``; issue #54).
    for name, rec in (("refined", final), ("raw", raw)):
        if rec.states is not None:
            arrays[STATE_KEYS[name]] = rec.states
        if rec.controls is not None:
            arrays[CONTROL_KEYS[name]] = rec.controls
    if final.states is not None:
        arrays[PRESETTLE_STATE_KEY] = presettle_state(prep)
    if final.contact_frames is not None:
        arrays["object_table_contact"] = final.contact_frames.table
    if final.articulation is not None and raw.articulation is not None and prep.seq.articulation is not None:
        arrays["object_articulation_sim"] = final.articulation
        arrays["object_articulation_ref"] = prep.seq.articulation
        arrays["raw_object_articulation_sim"] = raw.articulation
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
        if isinstance(ref, RobotReference):  # a robot hand (issue #55): its joints as simulated and retargeted
            arrays[f"{s}_q_sim"] = final.joints[s]
            arrays[f"{s}_actuator_force_peak"] = final.joint_force[s]
            arrays[f"{s}_q_retarget"] = ref.q
            arrays[f"{s}_human_keypoints"] = ref.human_keypoints
        if getattr(ref, "from_mano", False):
            # The refined hand as MANO parameters (issue #6): exact because the scene used the MANO geometry.
            hand = prep.seq.hand(s)
            assert hand is not None
            arrays.update(mano_result_arrays(prep.seq, hand, p, r, q, prep.mano_dir))
    for name, m in (("raw", m_raw), ("refined", m_ref)):
        for key, val in m["per_frame"].items():
            arrays[f"metrics_{name}_{key}"] = val
    arrays.update(final.contacts)
    return arrays


def attempt_figures(m: dict[str, Any]) -> dict[str, Any]:
    """An attempt's entry in the summary: success and object errors on both protocols."""
    paper = m["paper"]
    return {"success": bool(m["success"]), "E_t": m["E_t"], "E_r": m["E_r"],
            "paper": {"success": bool(paper["success"]), "E_t": paper["E_t"], "E_r": paper["E_r"]}}


def add_attempt_metrics(m_ref: dict[str, Any], attempts: list[dict[str, Any]]) -> None:
    """The first attempt's success beside the final one (issue #15 item 3; the paper runs one attempt)."""
    if not attempts:
        return
    m_ref["attempts"] = len(attempts)
    m_ref["success_first_attempt"] = bool(attempts[0]["success"])
    if "paper" in m_ref and "paper" in attempts[0]:
        m_ref["paper"]["success_first_attempt"] = bool(attempts[0]["paper"]["success"])
