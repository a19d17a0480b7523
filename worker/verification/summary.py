"""``verify``'s summary checks: metrics (both protocols, plausibility), attempts and sequence facts against the
fresh derivation, exactly on the build that made the result and within ``Tolerances`` elsewhere."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from common.outcome import ReasonCode
from worker.refine.derive import add_attempt_metrics, attempt_figures
from worker.refine.outcome import classify_outcome, was_rescued
from worker.simulation.metrics import scalar_metrics
from worker.simulation.table_fit import TableFit, score_margin
from worker.verification.report import CROSS_HOST, Tolerances, VerifyReport


def check_summary(
    report: VerifyReport, summary: dict[str, Any], derived: Any, attempt_kf: list[Any] | None,
    tol: Tolerances | None, attempt_tol: Tolerances | str | None = "same", attempts_decide: bool = True,
) -> None:
    """The summary's metrics (raw, refined, both protocols), attempts, success and sequence facts against the
    derivation (``arrays.check_stored_metrics`` checks them against the stored trajectories). ``attempt_tol``:
    the tolerance of the restarts' figures (each attempt's, the first attempt's success) where it is not ``tol``;
    ``attempts_decide`` False: their differences beyond it are notes, not failures (a stepwise check off the
    original build: no restart's states are stored, so they are whole re-simulations, which drift off-host)."""
    kinds = tuple(j.kind for j in derived.prep.seq.object.joints)
    tol = None if tol is None else tol.for_joints(kinds)
    a_tol = tol if isinstance(attempt_tol, str) else None if attempt_tol is None else attempt_tol.for_joints(kinds)
    sink = report if attempts_decide else VerifyReport()
    stored = summary.get("metrics", {})
    attempts = summary.get("attempts") or []
    fresh = {k: scalar_metrics(v) for k, v in derived.metrics.items()}
    if attempt_kf is not None:
        fresh_attempts = [attempt_figures(m) for m in derived.attempt_metrics]
    elif len(attempts) <= 1:
        fresh_attempts = [attempt_figures(derived.metrics["refined"])]
    else:
        fresh_attempts = []
        report.config_notes.append("restarts' keyframes not stored (older result): attempts not re-simulated")
    add_attempt_metrics(fresh["refined"], fresh_attempts if len(attempts) == len(fresh_attempts) else [])
    for name in ("raw", "refined"):
        if name not in stored:
            report.failures.append(f"metrics.{name}: missing")
            continue
        for key in ("E_t", "E_r", "E_j", "E_ft", "success"):
            if key not in stored[name]:
                report.failures.append(f"metrics.{name}.{key}: missing")
        first = ("success_first_attempt",)  # from the restarts' re-simulations
        mine = {k: v for k, v in stored[name].items() if k not in first}
        if isinstance(mine.get("paper"), dict):
            mine["paper"] = {k: v for k, v in mine["paper"].items() if k not in first}
        _compare_dict(report, f"metrics.{name}", mine, fresh[name], tol)
        _compare_dict(sink, f"metrics.{name}", {k: v for k, v in stored[name].items() if k in first},
                      fresh[name], a_tol)
        _compare_dict(sink, f"metrics.{name}.paper",
                      {k: v for k, v in stored[name].get("paper", {}).items() if k in first},
                      fresh[name].get("paper", {}), a_tol)
    if attempts and fresh_attempts:
        if len(attempts) != len(fresh_attempts):
            report.failures.append(f"attempts: {len(attempts)} listed, {len(fresh_attempts)} re-simulated")
        for i, (a, b) in enumerate(zip(attempts, fresh_attempts, strict=False)):
            _compare_dict(sink, f"attempts[{i}]", {k: v for k, v in a.items() if k in b}, b, a_tol)
    if sink is not report and (sink.failures or sink.config_notes):
        report.config_notes.append(
            "restarts re-simulated whole (their states are not stored), beyond the cross-host tolerance here, "
            "reported, not pass/fail: " + "; ".join(sink.failures + sink.config_notes))
    # What the preparation decided (the table under the object) and the simple facts about the sequence.
    prep = derived.prep
    facts = {"sequence": prep.seq.name, "fps": float(prep.seq.fps), "frames": int(prep.num_frames),
             "table": prep.scene.table_summary(), "object_hold": prep.scene.hold_summary()}
    if tol is None:
        facts["num_contacts"] = len(derived.final.contacts["contact_frame"])
    stored_facts = {**summary}
    if isinstance(summary.get("table"), dict):  # the drift: a simulated score, checked with the choice
        stored_facts["table"] = {k: v for k, v in summary["table"].items() if k != "drift"}
    for key, value in facts.items():
        if key in stored_facts:
            _compare_dict(report, key, stored_facts[key], value, tol)
    check_table(report, summary, prep.scene.table_fit)
    report.checked.extend(["summary.metrics", "summary.attempts", "summary.config", "summary.table"]
                          + (["summary.object_hold"] if "object_hold" in summary else []))


def check_table(report: VerifyReport, summary: dict[str, Any], fit: TableFit | None) -> None:
    """A result that records its table choice (``TableChoice``) stands on it in the re-derivation; here: the fit
    re-derives it as a candidate, scoring within ``table_fit.score_margin`` of the best here (two candidates near a
    tie swap under other CPU kernels), and the stored drift is within that margin of its score here. A result
    without the choice was checked the old way: the fit's own choice must be the stored plane (``check_summary``)."""
    table = summary.get("table")
    if not isinstance(table, dict) or "candidate" not in table:
        return
    if fit is None:
        report.failures.append("table: the scene records no table fit to check the stored choice against")
        return
    problems = fit.choice_problems()
    report.failures.extend(problems)
    stored = table.get("drift")
    margin = score_margin(max(float(stored), fit.drift)) if isinstance(stored, int | float) else 0.0
    if not isinstance(stored, int | float) or not abs(float(stored) - fit.drift) <= margin:
        report.failures.append(f"table.drift: stored {stored!r}, re-computed {fit.drift:.4g} (tolerance "
                               f"{margin:.3g} degrees + mm)")
    best = int(np.argmin(fit.scores)) if fit.scores else fit.candidate
    if best != fit.candidate and not problems:
        report.config_notes.append(
            f"table: the stored candidate {fit.candidate} scores {fit.scores[fit.candidate]:.4g} here, candidate "
            f"{best} {fit.scores[best]:.4g} (within the margin {score_margin(fit.scores[fit.candidate]):.3g}: a near "
            "tie the kernels decide)")


def check_outcome(report: VerifyReport, summary: dict[str, Any], derived: Any, tol: Tolerances | None,
                  cache_dir: Path | None = None) -> None:
    """The stored outcome (``summary["outcome"]``, absent from results made before it) against one classified
    again from the derivation (``worker.refine.outcome``). ``plan_cut_short`` is a fact of the optimisation, not of
    the replay: its value is checked against the attempts' evaluations. On another host a reason found from the
    simulation may move by a frame where the trajectory does (a note); ``executable`` is always the stored
    paper-protocol success (which ``check_stored_metrics`` checks against the stored trajectory)."""
    stored = summary.get("outcome")
    if stored is None:
        return
    contact = derived.final.contact_frames
    fresh = classify_outcome(derived.prep, derived.metrics["refined"], derived.final.object_pose,
                             hand_contact=None if contact is None else contact.hand,
                             rescued=was_rescued(derived.prep), cache_dir=cache_dir).model_dump(mode="json")
    cut = [r for r in stored.get("reasons") or [] if r.get("code") == ReasonCode.PLAN_CUT_SHORT]
    kept = {**stored, "reasons": [r for r in stored.get("reasons") or [] if r not in cut]}
    evaluations = sum(int(a.get("evaluations", 0)) for a in summary.get("attempts") or [])
    for r in cut:
        if r.get("value") != evaluations:
            report.failures.append(f"outcome: plan_cut_short says {r.get('value')} evaluations, the attempts "
                                   f"{evaluations}")
    if tol is None:
        _compare_dict(report, "outcome", kept, fresh, tol)
    elif kept != fresh:  # as a success near its threshold may flip there (``_near_threshold``)
        report.config_notes.append("outcome differs on re-simulation (within the trajectory's cross-host "
                                   "tolerance)")
    if bool(kept.get("executable")) != bool(summary.get("metrics", {}).get("refined", {}).get("paper", {})
                                            .get("success")):
        report.failures.append("outcome.executable: not the stored paper-protocol success")
    report.checked.append("summary.outcome")


def _compare_dict(report: VerifyReport, path: str, stored: Any, fresh: Any, tol: Tolerances | None) -> None:
    if isinstance(fresh, dict):
        if not isinstance(stored, dict):
            report.failures.append(f"{path}: not a mapping")
            return
        for key, value in stored.items():
            if key not in fresh:
                if path.endswith("paper") or key in ("attempts", "success_first_attempt"):
                    report.failures.append(f"{path}.{key}: stored but not re-computed")
                continue  # e.g. figures of a newer version
            _compare_dict(report, f"{path}.{key}", value, fresh[key], tol)
        return
    name = path.rsplit(".", 1)[-1]
    if isinstance(fresh, str) or isinstance(stored, str):
        if stored != fresh:
            report.failures.append(f"{path}: stored {stored!r}, re-computed {fresh!r}")
        return
    if isinstance(fresh, list | tuple):
        if not isinstance(stored, list | tuple) or len(stored) != len(fresh):
            report.failures.append(f"{path}: stored {stored!r}, re-computed {list(fresh)!r}")
            return
        for i, (a, b) in enumerate(zip(stored, fresh, strict=True)):
            _compare_dict(report, f"{path}[{i}]", a, b, tol)
        return
    if isinstance(fresh, bool) or isinstance(stored, bool):
        if bool(stored) != bool(fresh) or type(stored) is not type(fresh):
            if tol is not None and tol.contact_rows is None and name.startswith("success") \
                    and _near_threshold(path, report):
                return
            report.failures.append(f"{path}: stored {stored!r}, re-computed {fresh!r}")
        return
    if fresh is None or stored is None:
        if fresh is not None or stored is not None:
            report.failures.append(f"{path}: stored {stored!r}, re-computed {fresh!r}")
        return
    if not isinstance(stored, int | float):
        report.failures.append(f"{path}: stored {stored!r} is not a number")
        return
    a, b = float(stored), float(fresh)
    if np.isnan(a) and np.isnan(b):
        return
    # Counts are exact; other figures without a physical tolerance (and all of them where the replay is exact)
    # may differ in the last bits NumPy's CPU-specific kernels leave (``Tolerances.figures_last_bits``).
    physical = None if tol is None or np.isnan(b) else tol.summary_limit(name, abs(b))
    counts = ("frames", "lifted_frames", "first_frame", "attempts")
    limit = None if name in counts or np.isnan(b) else physical or (tol or CROSS_HOST).figures_last_bits
    diff = abs(a - b) if not (np.isnan(a) or np.isnan(b)) else float("inf")
    if (limit is None and a != b) or (limit is not None and diff > limit):
        report.failures.append(f"{path}: stored {a:.6g}, re-computed {b:.6g} (difference {diff:.3g}"
                               f"{'' if limit is None else f', tolerance {limit:g}'})")


def _near_threshold(path: str, report: VerifyReport) -> bool:
    """On another host a success may flip where the re-simulated trajectory crosses a threshold within the
    tolerance: noted, not failed. The stored success is still checked exactly against the stored trajectory
    (``check_stored_metrics``), and that trajectory against the re-simulation within the tolerance."""
    report.config_notes.append(f"{path} differs on re-simulation (within the trajectory's cross-host tolerance)")
    return True
