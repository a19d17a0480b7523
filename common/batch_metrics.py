"""What the service reads out of result summaries: the outcome, per-protocol metrics, and batch aggregates
(issue #20 item 1, issue #53 items 1 and 6).

A result summary carries ``metrics = {"raw": {...}, "refined": {...}}`` computed over all frames; each stage
nests the paper's protocol (frames 10 onward) as ``metrics[stage]["paper"]``. Other protocols are also read by
key from ``summary["protocols"][name]`` or ``summary["metrics"][name]`` with the same ``raw`` / ``refined``
layout, so a further protocol shows up in the aggregate and the report without a change here. Metric keys are
the worker's (``E_t`` cm, ``E_r`` deg, ``E_j`` / ``E_ft`` cm, ``success``, penetration in mm); older results
spelled the errors with units (``E_t_cm``), which are read too.

The outcome (``summary["outcome"]``: ``executable``, the ``protocol`` it is judged on, and ``reasons``, each
``{code, frame, value, unit, message}``) is reduced here to what the queue stores beside a job
(``outcome_columns``): a status for filtering and counting, and a short form for listings.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from common.outcome import FAILURE_CODES

#: The protocol every summary has: ``summary["metrics"]`` itself.
ALL_FRAMES = "all_frames"
STAGES: tuple[str, ...] = ("raw", "refined")
#: Metric key -> the name of its mean in the aggregate ("success" becomes the success rate, SR).
METRICS: dict[str, str] = {
    "success": "SR",
    "E_t": "E_t",
    "E_r": "E_r",
    "E_j": "E_j",
    "E_ft": "E_ft",
    "penetration_mean_mm": "penetration_mean_mm",
    "penetration_max_mm": "penetration_max_mm",
}
_UNIT_SUFFIX = {"E_t": "_cm", "E_r": "_deg", "E_j": "_cm", "E_ft": "_cm"}

#: A job's outcome status: the refined sequence passes the outcome's protocol (executable) or not; ``unknown``
#: for a result that carries no outcome.
EXECUTABLE, NOT_EXECUTABLE, UNKNOWN = "executable", "not_executable", "unknown"
OUTCOMES: tuple[str, ...] = (EXECUTABLE, NOT_EXECUTABLE, UNKNOWN)
#: Reasons kept in a job's short form (the result summary keeps them all).
MAX_LISTED_REASONS = 8
_REASON_TEXT_LIMIT = 500


def finite_number(value: Any) -> float | None:
    """A metric as a float (a bool as 0/1); None for anything else or a non-finite number."""
    if isinstance(value, bool):
        return float(value)
    if isinstance(value, (int, float)) and math.isfinite(value):
        return float(value)
    return None


def protocol_sections(summary: Mapping[str, Any] | None) -> dict[str, Mapping[str, Any]]:
    """``{protocol: {"raw": {...}, "refined": {...}}}`` found in one result summary."""
    if not summary:
        return {}
    metrics = summary.get("metrics")
    out: dict[str, Mapping[str, Any]] = {}
    if isinstance(metrics, Mapping):
        out[ALL_FRAMES] = metrics
        nested: dict[str, dict[str, Mapping[str, Any]]] = {}
        for stage in STAGES:
            block = metrics.get(stage)
            if not isinstance(block, Mapping):
                continue
            for name, section in block.items():
                if isinstance(section, Mapping) and any(k in section for k in ("E_t", "success")):
                    nested.setdefault(str(name), {})[stage] = section
        out.update(nested)
        for name, section in metrics.items():
            if name not in STAGES and isinstance(section, Mapping) and any(s in section for s in STAGES):
                out[str(name)] = section
    protocols = summary.get("protocols")
    if isinstance(protocols, Mapping):
        out.update({str(k): v for k, v in protocols.items() if isinstance(v, Mapping)})
    return out


def metric_value(stage: Any, key: str) -> float | None:
    """One metric of one stage as a float (success as 0/1); None when absent or not finite."""
    if not isinstance(stage, Mapping):
        return None
    for name in (key, key + _UNIT_SUFFIX.get(key, "")):
        value = finite_number(stage.get(name))
        if value is not None:
            return value
    return None


def aggregate(summaries: Iterable[Mapping[str, Any] | None]) -> dict[str, dict[str, dict[str, Any]]]:
    """``{protocol: {stage: {"n": sequences, "SR": .., "E_t": .., ...}}}``: means over the summaries that have
    each metric (None when none has it). ``n`` counts summaries with that protocol and stage."""
    sums: dict[str, dict[str, dict[str, list[float]]]] = {}
    counts: dict[str, dict[str, int]] = {}
    for summary in summaries:
        for protocol, section in protocol_sections(summary).items():
            for stage in STAGES:
                if not isinstance(section.get(stage), Mapping):
                    continue
                counts.setdefault(protocol, {}).setdefault(stage, 0)
                counts[protocol][stage] += 1
                per_metric = sums.setdefault(protocol, {}).setdefault(stage, {})
                for key in METRICS:
                    value = metric_value(section[stage], key)
                    if value is not None:
                        per_metric.setdefault(key, []).append(value)
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for protocol, stages in counts.items():
        out[protocol] = {}
        for stage, n in stages.items():
            values = sums[protocol][stage]
            row: dict[str, Any] = {"n": n}
            for key, label in METRICS.items():
                row[label] = sum(values[key]) / len(values[key]) if values.get(key) else None
            out[protocol][stage] = row
    return out


def report_columns(summary: Mapping[str, Any] | None) -> dict[str, float | None]:
    """Flat ``{protocol}_{stage}_{metric}`` columns of one summary, for the per-sequence report."""
    row: dict[str, float | None] = {}
    for protocol, section in protocol_sections(summary).items():
        for stage in STAGES:
            for key, label in METRICS.items():
                row[f"{protocol}_{stage}_{label}"] = metric_value(section.get(stage), key)
    return row


# ---------------------------------------------------------------------- the outcome
def outcome_of(summary: Mapping[str, Any] | None) -> Mapping[str, Any] | None:
    """The summary's ``outcome`` (also read from ``metrics.outcome``), or None when it has none."""
    if not isinstance(summary, Mapping):
        return None
    metrics = summary.get("metrics")
    for holder in (summary, metrics if isinstance(metrics, Mapping) else {}):
        outcome = holder.get("outcome")
        if isinstance(outcome, Mapping) and isinstance(outcome.get("executable"), bool):
            return outcome
    return None


def outcome_status(summary: Mapping[str, Any] | None) -> str:
    """``executable``, ``not_executable``, or ``unknown`` (no outcome in the summary)."""
    outcome = outcome_of(summary)
    if outcome is None:
        return UNKNOWN
    return EXECUTABLE if outcome["executable"] else NOT_EXECUTABLE


def _text(value: Any) -> str | None:
    return value[:_REASON_TEXT_LIMIT] if isinstance(value, str) else None


def reasons(outcome: Mapping[str, Any] | None) -> list[dict[str, Any]]:
    """The outcome's reasons in the contract's shape (code, frame, value, unit, message); malformed ones skipped."""
    raw = outcome.get("reasons") if isinstance(outcome, Mapping) else None
    out: list[dict[str, Any]] = []
    for item in raw if isinstance(raw, list) else []:
        if not isinstance(item, Mapping) or not isinstance(item.get("code"), str):
            continue
        frame = item.get("frame")
        out.append({
            "code": item["code"][:100],
            "frame": frame if isinstance(frame, int) and not isinstance(frame, bool) else None,
            "value": finite_number(item.get("value")) if not isinstance(item.get("value"), bool) else None,
            "unit": _text(item.get("unit")),
            "message": _text(item.get("message")) or "",
        })  # fmt: skip
    return out


def primary_reason(items: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The most telling reason: the first that explains a failure, else the first (e.g. a rescue)."""
    return next((r for r in items if r["code"] in FAILURE_CODES), items[0] if items else None)


def headline_metrics(summary: Mapping[str, Any] | None, protocol: str | None) -> dict[str, float | None]:
    """The refined E_t (cm) and E_r (deg) on ``protocol`` (all frames when the summary lacks it)."""
    sections = protocol_sections(summary)
    section = sections.get(protocol or ALL_FRAMES) or sections.get(ALL_FRAMES) or {}
    refined = section.get("refined")
    return {"E_t": metric_value(refined, "E_t"), "E_r": metric_value(refined, "E_r")}


def outcome_columns(summary: Mapping[str, Any] | None) -> tuple[str, dict[str, Any]]:
    """What the queue stores beside a SUCCEEDED job: (status, short form). The short form holds the protocol
    (None when unknown), the first ``MAX_LISTED_REASONS`` reasons, how many there are, and the refined E_t /
    E_r on that protocol (``protocol_metrics``: which protocol they are on)."""
    outcome = outcome_of(summary)
    listed = reasons(outcome)
    protocol = outcome.get("protocol") if outcome is not None else None
    protocol = protocol if isinstance(protocol, str) else None
    sections = protocol_sections(summary)
    measured_on = protocol if protocol in sections else ALL_FRAMES if ALL_FRAMES in sections else None
    detail: dict[str, Any] = {
        "protocol": protocol,
        "reasons": listed[:MAX_LISTED_REASONS],
        "reasons_total": len(listed),
        "protocol_metrics": measured_on,
        **headline_metrics(summary, measured_on),
    }
    return outcome_status(summary), detail
