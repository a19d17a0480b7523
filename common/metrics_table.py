"""The one metrics table (DESIGN §1.8): raw replay vs refined, for one result or as means over a dataset.

Used by ``hoi-refine replay``, ``refine``, ``demo`` and the closing summary of ``submit``. Columns are named
runs ("raw", "refined", or "raw replay" / "refined" means); each column is a mapping of metric key to value as
results store them (``E_t`` cm, ``E_r`` deg, ...; unit-suffixed spellings such as ``E_t_cm`` of older results
are read too). ``success`` is a bool for one result and a rate (0..1) for a mean. Both protocols (issue #15):
all frames, and the paper's (``paper.*``: frames 10 onward), the first attempt's success beside the final one,
and the plausibility figures (penetration, hand-held share of lifted frames); rows a result lacks are left out.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from rich.table import Table

#: Rows in order: key, label, unit, format. The worst-frame rows appear only when a column has them.
ROWS: tuple[tuple[str, str, str, str], ...] = (
    ("E_t", "object position error E_t", "cm", "{:.2f}"),
    ("E_r", "object rotation error E_r", "deg", "{:.2f}"),
    ("E_j", "hand joint error E_j", "cm", "{:.2f}"),
    ("E_ft", "fingertip error E_ft", "cm", "{:.2f}"),
    ("E_a", "articulation error E_a (largest joint; cm if sliding)", "deg", "{:.2f}"),
    ("max_E_t", "worst-frame position error", "cm", "{:.2f}"),
    ("max_E_r", "worst-frame rotation error", "deg", "{:.1f}"),
    ("paper.E_t", "E_t, paper's protocol (frames 10+)", "cm", "{:.2f}"),
    ("paper.E_r", "E_r, paper's protocol (frames 10+)", "deg", "{:.2f}"),
    ("paper.E_j", "E_j, paper's protocol (frames 10+)", "cm", "{:.2f}"),
    ("paper.E_ft", "E_ft, paper's protocol (frames 10+)", "cm", "{:.2f}"),
    ("paper.E_a", "E_a, paper's protocol (frames 10+)", "deg", "{:.2f}"),
    ("penetration_mean_mm", "penetration: mean per-frame maximum", "mm", "{:.2f}"),
    ("penetration_max_mm", "penetration: sequence maximum", "mm", "{:.2f}"),
    ("hand_only_fraction", "lifted frames held by the hand alone", "", "{:.0%}"),
)
#: Rows shown only when a column has them (older results, the raw replay for the first attempt, a rigid object's
#: results for E_a).
OPTIONAL_PREFIXES: tuple[str, ...] = ("max_", "paper.", "penetration_", "hand_only", "E_a")
SUCCESS_LABEL = "success (every frame E_t <= 3 cm, E_r <= 30 deg)"
#: An articulated object's success also bounds its joints (worker.simulation.metrics.SUCCESS_ARTICULATION; common
#: cannot import the worker, so a test ties the two).
ARTICULATED_SUCCESS_LABEL = "success (every frame E_t <= 3 cm, E_r <= 30 deg, E_a <= 15 deg | 3 cm)"
#: Success rows after the first: key, label.
SUCCESS_ROWS: tuple[tuple[str, str], ...] = (
    ("paper.success", "success, paper's protocol (frames 10+)"),
    ("success_first_attempt", "success of the first attempt (no restart)"),
)
_UNIT_SUFFIX = {"E_t": "_cm", "E_r": "_deg", "E_j": "_cm", "E_ft": "_cm"}
#: The keys a mean over many results is taken of (the submit summary): every row but the worst-frame ones, then
#: the success rates.
MEAN_KEYS: tuple[str, ...] = (
    *(key for key, _, _, _ in ROWS if not key.startswith("max_")),
    "success",
    *(key for key, _ in SUCCESS_ROWS),
)


def metric_value(column: Mapping[str, Any], key: str) -> Any:
    """``column[key]``, or its unit-suffixed spelling (``E_t_cm``) in results written before the units moved
    into the documentation; a dotted key reads a nested block (``paper.E_t``); None when absent."""
    if key in column:  # a flat key, also a dotted one (``paper.E_t``) of a mean over results
        return column[key]
    if "." in key:
        block, _, rest = key.partition(".")
        inner = column.get(block)
        return metric_value(inner, rest) if isinstance(inner, Mapping) else None
    return column.get(key + _UNIT_SUFFIX.get(key, "\0"))


def _cell(value: Any, fmt: str) -> str:
    if value is None:
        return "-"
    try:
        number = float(value)
    except (TypeError, ValueError):
        return str(value)
    return "-" if number != number else fmt.format(number)  # NaN: no valid frame to measure on


def _success_cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    return f"{float(value):.0%}"


def metrics_table(columns: Mapping[str, Mapping[str, Any]], title: str | None = None) -> Table:
    """A rich table with one column per run, e.g. ``{"raw": summary["metrics"]["raw"], "refined": ...}``."""
    table = Table(title=title)
    table.add_column("metric")
    table.add_column("unit")
    for name in columns:
        table.add_column(name, justify="right")
    for key, label, unit, fmt in ROWS:
        values = [metric_value(c, key) for c in columns.values()]
        if key.startswith(OPTIONAL_PREFIXES) and all(v is None for v in values):
            continue
        table.add_row(label, unit, *(_cell(v, fmt) for v in values))
    articulated = any(metric_value(c, "E_a") is not None for c in columns.values())
    label = ARTICULATED_SUCCESS_LABEL if articulated else SUCCESS_LABEL
    table.add_row(label, "", *(_success_cell(metric_value(c, "success")) for c in columns.values()))
    for key, label in SUCCESS_ROWS:
        values = [metric_value(c, key) for c in columns.values()]
        if any(v is not None for v in values):
            table.add_row(label, "", *(_success_cell(v) for v in values))
    return table


def run_footer(summary: Mapping[str, Any]) -> str:
    """One line on how a refinement ran (wall time, simulation share, steps, evaluations, windows), and one on
    its restarts when there were any."""
    t = summary.get("timings", {})
    w = summary.get("windows", {})
    lines = [
        f"wall {t.get('wall_s', 0):.1f}s, {t.get('sim_share', 0) * 100:.0f}% in simulation, "
        f"{t.get('steps', 0)} steps, {t.get('evaluations', 0)} candidate evaluations, "
        f"windows {w.get('count', 0)} ({w.get('skipped', 0)} skipped, {w.get('escalated', 0)} escalated)"
    ]
    attempts = summary.get("attempts", [])
    if len(attempts) > 1:
        seeds = ", ".join(f"{'polish, ' if a.get('polish') else ''}seed {a['seed']}: "
                          f"{'ok' if a['success'] else 'failed'}" for a in attempts)
        lines.append(f"{len(attempts)} attempts ({seeds}); the result is the best")
    return "\n".join(lines)


def outcome_lines(summary: Mapping[str, Any]) -> list[str]:
    """The result's outcome first (``common.outcome``): executable or not on the paper's protocol, then each reason
    (code, frame, value) with its sentence, most telling first; nothing for a summary without one."""
    from common.outcome import outcome_of

    outcome = outcome_of(dict(summary))
    if outcome is None:
        return []
    verdict = "executable" if outcome.executable else "NOT executable"
    lines = [f"outcome: {verdict} (the paper's protocol: every frame from 10 on within 3 cm / 30 deg)"]
    for r in outcome.reasons:
        where = [f"frame {r.frame}"] if r.frame is not None else []
        if r.value is not None:
            where.append(f"{r.value:g} {r.unit or ''}".rstrip())
        detail = f" ({', '.join(where)})" if where else ""
        lines.append(f"  {r.code.value}{detail}: {r.message}")
    return lines
