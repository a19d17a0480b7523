"""``verify``: recompute everything a refinement result claims and compare (issue #15 item 1).

From the embedded sequence (or ``--sequence``) and the stored keyframes, ``worker.refine.derive.derive_result``
runs again — the same function that made the result — in a fresh model: the raw and the refined replay (and each
restart), contacts, every derived array and both protocols' metrics. Then:

1. **Config.** The stored physics config (``config.sim``, the rotation pivot) against the product's defaults for
   the result's version: a setting the result does not record reads as the default of the versions before it
   existed (``OLDER_DEFAULTS``); any other difference is reported by name, default and stored value, and fails
   unless ``allow_config`` (the re-simulation always uses the stored config).
2. **Consistency** (tight, whatever the host): the summary metrics recomputed from the stored trajectories and
   contacts, the stored per-frame metric arrays, the contacts' object-frame points against their world points
   and the stored object pose, the first attempt's success.
3. **Re-simulation.** Every stored array and summary figure against the fresh derivation. On the build that made
   the result the replay is bit-identical (``exact``), and then everything must be equal but the figures
   (per-frame and summary), which NumPy computes with CPU-specific kernels and so may differ in their last bits
   even where the replay is exact on another host (``Tolerances.figures_last_bits``). On another host it is
   usually not exact: NumPy and OpenBLAS pick CPU-specific kernels (AVX-512 or AVX2) whose last bits differ, and
   contact-rich dynamics grow a 1e-16 difference into millimetres (measured: ``CROSS_HOST``). Then each field is
   compared within a physical tolerance instead (``Tolerances``).

4. **Stepwise** (a result that stores every frame's integration state, issue #54): both replays checked frame by
   frame against their stored states (``worker.verification.stepwise``), and every array and figure of 2-3
   compared with the records made at those states: exact where each frame was reached bit for bit, else within
   ``STEPWISE`` (micrometres and below); the whole re-simulation's drift is then a reported figure, not the test.
   A result without states (older) is checked as in 3, with a note saying so.

The table under the object: a result that records the fit's choice (``summary["table"]["candidate"]``, since
issue #54) is re-derived on that very plane and start pose, and passes where the fit re-derives it as a candidate
scoring within ``worker.simulation.table_fit.score_margin`` of the best here (near ties swap under other kernels);
an older result must come out on the same plane as the fit's own choice here.

Any difference fails naming the field and its largest difference. The report carries a SHA-256 over everything
that was checked (stored arrays and summary parts), so two parties can tell they checked the same content.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from common.errors import ResultMismatchError, UnsupportedFormatError
from common.job_options import JobOptions
from common.result_format import read_arrays, read_summary
from common.sequence import Sequence
from common.sequence_io import sequence_to_npz_bytes
from worker.refine.derive import STATE_KEYS, derive_result
from worker.refine.environment import versions
from worker.refine.prepare import MIRROR_LEFT_HAND, ROBOT_JOINT_SPEED, ROTATION_PIVOT
from worker.simulation.config import CONVEX_DETAILS, OLDER_SIM_DEFAULTS, SimConfig
from worker.simulation.table_fit import TableChoice
from worker.verification.arrays import ArrayChecker, check_stored_metrics
from worker.verification.report import CROSS_HOST, STEPWISE, Tolerances, VerifyReport
from worker.verification.stepwise import stepwise_derivation
from worker.verification.summary import check_outcome, check_summary

__all__ = ["CROSS_HOST", "Tolerances", "VerifyReport", "check_result", "verify_result"]

#: Settings a result does not record were, before they existed, these (``OLDER_SIM_DEFAULTS``); the hand turned
#: about the wrist.
OLDER_DEFAULTS: dict[str, Any] = OLDER_SIM_DEFAULTS
OLDER_PIVOT = "wrist"
#: Settings the refinement itself chooses per sequence among these values: not a non-default config as such
#: (``_check_rescue`` checks when the finer convex parts are the product's).
PRODUCT_CHOICES: dict[str, tuple[Any, ...]] = {"convex_detail": CONVEX_DETAILS}
#: Complete sets of physics defaults the product had before: a result made with one of them whole is checked
#: against that set (a note, not a failure); a mix of old and new values is a non-default config. The first set
#: a result matches is the one it is read with.
EARLIER_DEFAULTS: dict[str, dict[str, Any]] = {
    "before issue #19": {"noslip_iterations": 10, "impratio": 1.0, "contact_solimp": (0.9, 0.99, 0.001)},
    # A primitive known by its tessellation's vertices (recorded from 391fb14 on, the default until the flip).
    "before primitive surface points (issue #15)": {"primitive_surface_spacing_m": 0.0},
}


def verify_result(
    blob: bytes, sequence: Sequence | None = None, *, allow_config: bool = False, cache_dir: Path | None = None,
    mano_dir: Path | None = None,
) -> dict[str, Any]:
    """``check_result``, raising ``ResultMismatchError`` naming every failing field; returns the report as a dict
    (``VerifyReport.to_dict``)."""
    report = check_result(blob, sequence, allow_config=allow_config, cache_dir=cache_dir, mano_dir=mano_dir)
    if report.failures:
        raise ResultMismatchError("result does not verify:\n  " + "\n  ".join(report.failures))
    return report.to_dict()


def check_result(
    blob: bytes, sequence: Sequence | None = None, *, allow_config: bool = False, cache_dir: Path | None = None,
    mano_dir: Path | None = None, threads: int = 1,
) -> VerifyReport:
    """See the module docstring; failures are listed in the report, not raised. ``cache_dir`` and ``mano_dir``
    as for ``worker.refine.prepare.prepare`` (the command passes the configured folders); ``threads``: replays
    side by side (the same figures whatever the number)."""
    summary = read_summary(blob)
    if summary.get("kind") != "refine":
        raise UnsupportedFormatError(f"not a refinement result (kind {summary.get('kind')!r})")
    arrays = read_arrays(blob)
    if sequence is not None:
        seq_bytes = sequence_to_npz_bytes(sequence)
    elif "sequence_npz" in arrays:
        seq_bytes = arrays["sequence_npz"].tobytes()
    else:
        raise UnsupportedFormatError("the result embeds no sequence; pass --sequence")
    report = VerifyReport()
    config = summary.get("config", {})
    sim, pivot, mirror_left = _config(config, report, allow_config)
    options = JobOptions.model_validate(summary["options"])
    robot_speed = _robot_joint_speed(config, report) if options.hand is not None else True
    sides = list(summary.get("sides") or [k[: -len("_keyframes")] for k in arrays if k.endswith("_keyframes")
                                          and not k.endswith("_attempt_keyframes")])
    keyframes = {s: arrays.get(f"{s}_keyframes") for s in sides}
    attempt_kf = _attempt_keyframes(arrays, sides)
    details = _attempt_details(summary, attempt_kf, sim["convex_detail"])
    # The stored table choice (recorded since issue #54): the scene stands on it, ``check_table`` checks it.
    try:
        table = TableChoice.from_summary(summary["table"]) if isinstance(summary.get("table"), dict) else None
    except ValueError as exc:
        raise ResultMismatchError(str(exc)) from exc
    try:
        derived = derive_result(seq_bytes, options, SimConfig(**sim), pivot, keyframes,  # type: ignore[arg-type]
                                attempt_kf, cache_dir=cache_dir, mano_dir=mano_dir, mirror_left=mirror_left,
                                threads=threads, attempt_details=details, robot_speed_limits=robot_speed,
                                table=table)
    except ValueError as exc:
        raise ResultMismatchError(f"the stored controls do not fit the sequence: {exc}") from exc
    _check_rescue(report, sim["convex_detail"], details, derived.attempt_metrics, allow_config)
    ArrayChecker(report, arrays, derived.arrays).compare_trajectory()  # the whole rollout: exact, or its drift
    tol: Tolerances | None = None if report.exact else CROSS_HOST
    attempt_tol, attempts_decide = tol, True
    against = derived
    if any(key in arrays for key in STATE_KEYS.values()):
        report.method = "stepwise"
        against = stepwise_derivation(report, derived, arrays, seq_bytes, keyframes, threads)  # type: ignore[arg-type]
        if not report.exact:  # the whole rollout drifted (another host): a figure, the stepwise check decides
            # Even where every step is reached bit for bit (under the stored inputs), the arrays made of the
            # keyframes here (targets, wrist track) carry this host's last bits: the stepwise tolerances.
            tol, attempts_decide = STEPWISE, False
            report.config_notes.append(
                f"whole-rollout drift {report.max_pos_diff_m * 1000:.4g} mm / {report.max_rot_diff_deg:.4g} deg "
                "(reported, not pass/fail: every stored frame was checked against the one before it)")
    else:
        report.config_notes.append("no stored states (older result): verified against a whole re-simulation, "
                                   + ("bit-identical" if report.exact else "within the cross-host tolerances"))
    c = ArrayChecker(report, arrays, against.arrays)
    c.inputs(sides, tol)
    c.simulated(sides, tol)
    c.contacts(against, tol)
    c.consistency(against, sides)
    check_summary(report, summary, against, attempt_kf, tol, attempt_tol, attempts_decide)
    check_outcome(report, summary, against, tol, cache_dir)
    check_stored_metrics(report, arrays, summary, sides, tuple(j.kind for j in derived.prep.seq.object.joints))
    report.frames = int(derived.prep.num_frames)
    _environment_notes(summary.get("versions") or {}, report)
    # The digest covers every stored array the derivation makes (the same set on any host, whichever comparison
    # each got) and the summary parts compared; the rest (the optimisation's loss history) is named, unchecked.
    derived_keys = sorted(set(derived.arrays) & set(arrays))
    unchecked = sorted(set(arrays) - set(derived.arrays))
    if unchecked:
        report.config_notes.append(f"not re-computable, not checked: {', '.join(unchecked)}")
    report.digest = _digest(arrays, summary, derived_keys)
    return report


# ---------------------------------------------------------------------------------------------- config


def _robot_joint_speed(config: dict[str, Any], report: VerifyReport) -> bool:
    """Whether a robot hand's result was made with its retargeted motion within the joint speed limits
    (``config.robot_joint_speed``; robot results made before it have no key and were not)."""
    recorded = config.get("robot_joint_speed")
    if recorded is None:
        report.config_notes.append(f"robot_joint_speed not recorded (older result): read as "
                                   f"{ROBOT_JOINT_SPEED[False]!r}")
        return False
    if recorded not in ROBOT_JOINT_SPEED.values():
        raise UnsupportedFormatError(f"config.robot_joint_speed: unknown value {recorded!r}")
    return bool(recorded == ROBOT_JOINT_SPEED[True])


def _config(config: dict[str, Any], report: VerifyReport, allow_config: bool) -> tuple[dict[str, Any], str, bool]:
    """The stored sim settings (older defaults filled in), pivot and left-hand control convention (True: mirrored);
    config differences into the report."""
    defaults = SimConfig().to_dict()
    stored: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in config.get("sim", {}).items()}
    unknown = sorted(set(stored) - set(defaults))
    if unknown:
        raise UnsupportedFormatError(f"config.sim has settings this version does not know: {', '.join(unknown)}")
    recorded = set(stored)
    for name, default in defaults.items():
        if name not in recorded:  # the result predates the setting: the behaviour of its time
            stored[name] = OLDER_DEFAULTS.get(name, default)
            report.config_notes.append(f"{name} not recorded (older result): read as {stored[name]}")
    for era, earlier in EARLIER_DEFAULTS.items():
        if all(not _differs(stored[name], value) for name, value in earlier.items()):
            defaults = {**defaults, **earlier}
            report.config_notes.append(f"made with the product's physics defaults {era}: "
                                       + ", ".join(f"{k}={_plain(v)}" for k, v in earlier.items()))
            break
    for name, default in defaults.items():
        if name in recorded and _differs(stored[name], default) and stored[name] not in PRODUCT_CHOICES.get(name, ()):
            report.config_changes.append((f"sim.{name}", _plain(default), _plain(stored[name])))
    pivot = config.get("rotation_pivot")
    if pivot is None:
        pivot = OLDER_PIVOT
        report.config_notes.append(f"rotation_pivot not recorded (older result): read as {OLDER_PIVOT!r}")
    elif pivot != ROTATION_PIVOT:
        report.config_changes.append(("rotation_pivot", ROTATION_PIVOT, pivot))
    # Results made before issue #15 drove a left hand with the right hand's coordinates (no key recorded).
    left = config.get("left_hand_controls")
    current = "mirrored" if MIRROR_LEFT_HAND else "as right"
    if left is None:
        left = "as right"
        report.config_notes.append("left_hand_controls not recorded (older result): read as 'as right'")
    elif left != current:
        report.config_changes.append(("left_hand_controls", current, left))
    if report.config_changes and not allow_config:
        for name, default, value in report.config_changes:
            report.failures.append(f"config {name}: {value!r} differs from the default {default!r} "
                                   "(--allow-config accepts a non-default physics config)")
    return stored, str(pivot), left == "mirrored"


def _attempt_details(summary: dict[str, Any], attempt_kf: list[Any] | None, kept: str) -> list[str] | None:
    """The convex parts each stored attempt ran on (``SimConfig.convex_detail``): as its summary entry records
    (older results: all on the result's own)."""
    entries = summary.get("attempts") or []
    if attempt_kf is None or len(entries) != len(attempt_kf):
        return None  # the attempt count is checked against the re-simulation (``check_summary``)
    details = [str(a.get("convex_detail", kept)) if isinstance(a, dict) else kept for a in entries]
    unknown = sorted(set(details) - set(CONVEX_DETAILS))
    if unknown:
        raise UnsupportedFormatError(f"attempts ran on convex parts this version does not know: {', '.join(unknown)}")
    return details


def _check_rescue(report: VerifyReport, kept: str, details: list[str] | None, attempt_metrics: list[dict[str, Any]],
                  allow_config: bool) -> None:
    """A result on the finer convex parts is the product's only as a rescue (``worker.refine.run.rescue_due``):
    every attempt on the product's parts failed in the re-simulation. Otherwise it is a non-default config."""
    if kept == CONVEX_DETAILS[0]:
        return
    product = [m for d, m in zip(details or [], attempt_metrics, strict=False) if d == CONVEX_DETAILS[0]]
    if product and not any(m["success"] for m in product):
        report.config_notes.append(f"convex_detail {kept!r}: the rescue after {len(product)} failed attempt(s) on "
                                   f"the {CONVEX_DETAILS[0]} convex parts")
        return
    report.config_changes.append(("sim.convex_detail", CONVEX_DETAILS[0], kept))
    why = "no attempt on them" if not product else "an attempt on them succeeded"
    if not allow_config:
        report.failures.append(f"config sim.convex_detail: {kept!r} is the product's only when every attempt on the "
                               f"{CONVEX_DETAILS[0]!r} convex parts failed, and the result lists {why} "
                               "(--allow-config accepts a non-default physics config)")


def _environment_notes(stored: dict[str, Any], report: VerifyReport) -> None:
    """Name what differs between the environment that made the result and this one (package versions, CPU kind):
    where the replay is not bit-identical, that is why (a note, not a failure: the tolerances decide)."""
    here = versions()
    changed = [f"{k} {stored[k]} -> {here[k]}" for k in sorted(set(stored) & set(here)) if str(stored[k]) != here[k]]
    if changed:
        report.config_notes.append("made elsewhere (result -> here): " + "; ".join(changed))
    elif not report.exact and {"cpu", "numpy_simd"} <= set(stored):
        report.config_notes.append("the replay is not bit-identical although the result records this environment")


def _differs(a: Any, b: Any) -> bool:
    if isinstance(a, tuple | list) or isinstance(b, tuple | list):
        return list(a) != list(b) if isinstance(a, tuple | list) and isinstance(b, tuple | list) else True
    return bool(a != b)


def _plain(v: Any) -> Any:
    return list(v) if isinstance(v, tuple) else v


def _attempt_keyframes(arrays: dict[str, np.ndarray], sides: list[str]) -> list[dict[str, np.ndarray]] | None:
    stacks = {s: arrays.get(f"{s}_attempt_keyframes") for s in sides}
    if any(v is None for v in stacks.values()):
        return None
    n = {int(v.shape[0]) for v in stacks.values() if v is not None}
    if len(n) != 1:
        raise ResultMismatchError("attempt keyframes: the hands list different numbers of attempts")
    return [{s: np.asarray(v[i]) for s, v in stacks.items() if v is not None} for i in range(n.pop())]


def _digest(arrays: dict[str, np.ndarray], summary: dict[str, Any], keys: list[str]) -> str:
    """SHA-256 over the stored arrays ``keys`` (name, dtype, shape, bytes) and the checked summary parts."""
    h = hashlib.sha256()
    for key in keys:
        a = np.ascontiguousarray(arrays[key])
        h.update(f"{key}:{a.dtype.str}:{a.shape}:".encode())
        h.update(a.tobytes())
    parts = {k: summary.get(k) for k in ("metrics", "attempts", "config", "options", "seed", "sides", "frames",
                                         "fps", "sequence", "table", "num_contacts")}
    if "object_hold" in summary:  # recorded since the hold of unsupported objects; older digests stay as they were
        parts["object_hold"] = summary["object_hold"]
    h.update(json.dumps(parts, sort_keys=True).encode())
    return h.hexdigest()
