"""Aggregate raw-vs-refined metrics over a batch's result summaries (issue #20 item 1).

A result summary carries ``metrics = {"raw": {...}, "refined": {...}}`` computed over all frames (DESIGN
§1.8). Other protocols (the paper's, which drops each sequence's first 10 frames) are read by key from
``summary["protocols"][name]`` or ``summary["metrics"][name]`` with the same ``raw`` / ``refined`` layout, so
a second protocol shows up in the aggregate and the report without a change here. Keys are those of
``worker.metrics.METRIC_KEYS``; older results spelled them with units (``E_t_cm``), which are read too.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

#: The protocol every summary has: ``summary["metrics"]`` itself.
ALL_FRAMES = "all_frames"
STAGES: tuple[str, ...] = ("raw", "refined")
#: Metric key -> the name of its mean in the aggregate ("success" becomes the success rate, SR).
METRICS: dict[str, str] = {"success": "SR", "E_t": "E_t", "E_r": "E_r", "E_j": "E_j", "E_ft": "E_ft"}
_UNIT_SUFFIX = {"E_t": "_cm", "E_r": "_deg", "E_j": "_cm", "E_ft": "_cm"}


def protocol_sections(summary: Mapping[str, Any] | None) -> dict[str, Mapping[str, Any]]:
    """``{protocol: {"raw": {...}, "refined": {...}}}`` found in one result summary."""
    if not summary:
        return {}
    metrics = summary.get("metrics")
    out: dict[str, Mapping[str, Any]] = {}
    if isinstance(metrics, Mapping):
        out[ALL_FRAMES] = metrics
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
        value = stage.get(name)
        if isinstance(value, bool):
            return float(value)
        if isinstance(value, (int, float)) and math.isfinite(value):
            return float(value)
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
