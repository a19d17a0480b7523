"""The release's datasheet (``README.md``) and its plots, generated from the index table: counts, success on both
protocols, error distributions (PNG), failure reasons, software versions and physics configs, the layout, how to
load it, and every column with its unit (``common.release_format``)."""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from common.outcome import REASON_DESCRIPTIONS, ReasonCode
from common.release_format import (
    CONTACT_COLUMNS,
    CONTACTS_FILE,
    INDEX_COLUMNS,
    INDEX_FILE,
    METRICS,
    PLOTS_DIR,
    PROTOCOLS,
    RESULTS_DIR,
    STAGES,
    VERSIONED,
    Column,
    metric_column,
)
from common.release_manifest import MANIFEST_NAME

#: The datasheet's plots: file name -> (metric key, axis label) per panel.
PLOTS: dict[str, tuple[tuple[str, str], ...]] = {
    "object_errors.png": (("E_t", "mean object position error E_t (cm)"),
                          ("E_r", "mean object rotation error E_r (deg)")),
    "hand_and_penetration.png": (("E_j", "mean hand keypoint error E_j (cm)"),
                                 ("penetration_max_mm", "deepest penetration (mm)")),
}
_PROTOCOL_TEXT = {"all_frames": "all frames", "paper": "paper (frames 10 on)"}


def _values(rows: Sequence[dict[str, Any]], column: str) -> list[float]:
    return [float(r[column]) for r in rows if isinstance(r.get(column), (int, float)) and math.isfinite(r[column])]


def write_plots(rows: Sequence[dict[str, Any]], folder: Path) -> list[str]:
    """Histograms per sequence, raw replay against refined, on the paper protocol; returns the files written."""
    from matplotlib.figure import Figure  # the object API: no pyplot state, no display needed

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, panels in PLOTS.items():
        fig = Figure(figsize=(9, 3.4), layout="constrained")
        for ax, (key, label) in zip(fig.subplots(1, len(panels)), panels, strict=True):
            series = {stage: _values(rows, metric_column("paper", stage, key)) for stage in STAGES}
            data = [v for vs in series.values() for v in vs]
            if data:
                top = max(data) if max(data) > 0 else 1.0
                bins = [top * i / 20 for i in range(21)]
                for stage, color in zip(STAGES, ("tab:gray", "tab:blue"), strict=True):
                    if series[stage]:
                        ax.hist(series[stage], bins=bins, alpha=0.6, color=color,
                                label=f"{stage} (n={len(series[stage])})")
                ax.legend()
            ax.set_xlabel(label)
            ax.set_ylabel("sequences")
        fig.suptitle("per sequence, paper protocol (frames 10 on): raw replay vs refined")
        fig.savefig(folder / name, dpi=100, metadata={"Software": None})
        written.append(f"{PLOTS_DIR}/{name}")
    return written


def _reason_text(code: str) -> str:
    try:
        return REASON_DESCRIPTIONS.get(ReasonCode(code), "")
    except ValueError:  # a code this version does not know
        return ""


def _mean(values: list[float]) -> str:
    return f"{sum(values) / len(values):.3g}" if values else "–"


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c).replace("|", "\\|") for c in row) + " |" for row in rows]
    return lines


def _columns_table(columns: Sequence[Column], collapse_metrics: bool) -> list[str]:
    rows = []
    for c in columns:
        if collapse_metrics and c.name.startswith(tuple(f"{p}_" for p in PROTOCOLS)):
            continue
        rows.append((f"`{c.name}`", str(c.type), c.unit or "–", c.meaning))
    return _table(("column", "type", "unit", "meaning"), rows)


def columns_markdown() -> list[str]:
    """Both tables' columns with type, unit and meaning (the datasheet's last section, and docs/dataset.md's)."""
    out = [f"## Columns of `{INDEX_FILE}`", ""]
    out += _columns_table(INDEX_COLUMNS, collapse_metrics=True)
    out += ["", "Metric columns: `<protocol>_<stage>_<metric>`, protocol `all_frames` or `paper` (frames 10 on), "
            "stage `raw` (the retargeted replay) or `refined`; null where a result has no such figure:", ""]
    out += _table(("metric", "type", "unit", "meaning"),
                  [(f"`{k}`", str(t), u or "–", m) for k, (t, u, m) in METRICS.items()])
    out += ["", f"## Columns of `{CONTACTS_FILE}`", ""]
    out += _columns_table(CONTACT_COLUMNS, collapse_metrics=False)
    return out


def datasheet(title: str, source: str, rows: Sequence[dict[str, Any]], contacts: int, plots: list[str]) -> str:
    """The README.md text."""
    with_result = [r for r in rows if r.get("result_file")]
    outcomes = Counter(str(r["outcome"]) for r in with_result)
    no_result = Counter(str(r.get("job_state")) for r in rows if not r.get("result_file"))
    frames = sum(int(r["frames"] or 0) for r in with_result)
    out = [f"# {title}", "",
           f"A hoi-refine dataset release: {len(rows)} sequences from {source}. Each result is a MuJoCo replay in "
           "which the object moves only through contact; `hoi-refine verify` re-derives every figure from the "
           "result file itself (see *Checking it* below).", "", "## Counts", ""]
    out += _table(("sequences", "with a result", "executable", "not executable", "unknown", "without a result",
                   "frames", "contacts"),
                  [(len(rows), len(with_result), outcomes.get("executable", 0), outcomes.get("not_executable", 0),
                    outcomes.get("unknown", 0), len(rows) - len(with_result), frames, contacts)])
    if no_result:
        out += ["", "Jobs without a result, by state: " + ", ".join(f"{s} {n}" for s, n in sorted(no_result.items()))
                + " (their rows in `index.parquet` carry `job_state` and `job_error`)."]
    out += ["", "## Success and errors", "",
            "Means over the sequences with a result. Success: every frame within 3 cm / 30 deg of the recorded "
            "object (and within 15 deg per joint for an articulated object). The raw replay is the recording "
            "retargeted and replayed, before optimisation.", ""]
    table_rows = []
    for protocol in PROTOCOLS:
        for stage in STAGES:
            def col(key: str, protocol: str = protocol, stage: str = stage) -> list[float]:
                return _values(with_result, metric_column(protocol, stage, key))

            success = col("success")
            rate = f"{100 * sum(success) / len(success):.1f} % ({int(sum(success))}/{len(success)})" if success else "–"
            table_rows.append((_PROTOCOL_TEXT[protocol], stage, rate, _mean(col("E_t")), _mean(col("E_r")),
                               _mean(col("E_j")), _mean(col("E_ft")), _mean(col("penetration_max_mm"))))
    out += _table(("protocol", "stage", "success", "E_t (cm)", "E_r (deg)", "E_j (cm)", "E_ft (cm)",
                   "deepest penetration (mm)"), table_rows)
    out += ["", "## Error distributions", ""] + [f"![{Path(p).stem}]({p})" for p in plots]
    out += ["", "## Failure reasons", "",
            "The most telling reason of each sequence that is not executable (`reason` in `index.parquet`; "
            "every reason in `reasons`).", ""]
    reasons = Counter(str(r.get("reason") or "") for r in with_result if r.get("executable") is False)
    if reasons:
        out += _table(("reason", "sequences", "meaning"),
                      [(f"`{code}`" if code else "(none recorded)", n,
                        _reason_text(code) if code else "the result records no outcome reasons")
                       for code, n in reasons.most_common()])
    else:
        out += ["None: every sequence with a result is executable."]
    out += ["", "## Software and physics", "", "Versions recorded by the results (how many results each):", ""]
    version_rows = []
    for name in (*VERSIONED, "cpu", "numpy_simd"):
        column = name if name in ("cpu", "numpy_simd") else f"version_{name.replace('-', '_')}"
        seen = Counter(str(r[column]) for r in with_result if r.get(column))
        version_rows.append((name, ", ".join(f"{v} ({n})" for v, n in seen.most_common()) or "–"))
    out += _table(("package", "versions"), version_rows)
    physics = Counter(str(r["physics_json"]) for r in with_result if r.get("physics_json"))
    out += ["", f"Physics configs (MuJoCo settings, `physics_json`): {len(physics)} distinct.", ""]
    for i, (text, n) in enumerate(physics.most_common(), start=1):
        settings = json.loads(text)
        out += [f"Config {i} ({n} results):", "", "```"]
        out += [f"{k} = {json.dumps(v)}" for k, v in sorted(settings.items())] + ["```", ""]
    out += ["## Files", "", "```",
            "README.md           this datasheet",
            f"{INDEX_FILE}       one row per sequence",
            f"{CONTACTS_FILE}    one row per hand-object contact (all sequences)",
            f"{RESULTS_DIR}/NAME.result.npz   each sequence's result (format: hoi-refine's common/result_format.py)",
            f"{PLOTS_DIR}/*.png         the figures above",
            f"{MANIFEST_NAME}          SHA-256 of every other file",
            "```", "", "Reading it needs pandas (or pyarrow) only:", "", "```python",
            "import pandas as pd",
            f"index = pd.read_parquet('{INDEX_FILE}')",
            f"contacts = pd.read_parquet('{CONTACTS_FILE}')",
            "held = contacts[contacts.sequence == index.sequence[0]]",
            "```", "",
            "Units: lengths in metres in `contacts.parquet`; errors in cm / deg and penetration in mm in "
            "`index.parquet` (each Parquet field also carries its unit and meaning in its metadata).", "",
            "## Checking it", "",
            f"`sha256sum -c {MANIFEST_NAME}` checks every file's bytes. `hoi-refine verify .` re-simulates every "
            "result from its embedded sequence and stored controls and recomputes every contact, metric and "
            f"figure (in parallel; it also checks {MANIFEST_NAME} and that both tables say what the result files "
            "say); exit code 0 when all verify.", "",
            *columns_markdown()]
    return "\n".join(out) + "\n"
