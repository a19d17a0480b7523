"""The per-sequence report of a batch as CSV or Parquet (issue #20 item 1, issue #53 item 6).

One row per job, oldest first: identity, then the outcome first (``executable`` / ``not_executable`` /
``unknown``, the primary reason with its evidence, every reason's code), state, timing, the last error, whether
the worker's replay verified the stored result, and the raw / refined metrics of both protocols (all frames, and
the paper's: frames 10 onward) with penetration (``common.batch_metrics.report_columns``:
``all_frames_raw_E_t``, ``paper_refined_penetration_max_mm`` ...; further protocols a result carries follow).
Columns are the same for every row (a job without a result has nulls), so the file loads as a table.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from common.batch_metrics import (
    ALL_FRAMES,
    METRICS,
    STAGES,
    outcome_of,
    outcome_status,
    primary_reason,
    reasons,
    report_columns,
)
from common.job_state import JobState
from common.outcome import PROTOCOL
from common.queue_types import JobRecord

BASE_COLUMNS: tuple[tuple[str, pa.DataType], ...] = (
    ("job_id", pa.string()),
    ("name", pa.string()),
    ("outcome", pa.string()),
    ("reason", pa.string()),
    ("reason_frame", pa.int64()),
    ("reason_value", pa.float64()),
    ("reason_unit", pa.string()),
    ("reason_message", pa.string()),
    ("reasons", pa.string()),
    ("state", pa.string()),
    ("attempt", pa.int64()),
    ("frames", pa.int64()),
    ("created_at", pa.timestamp("us", tz="UTC")),
    ("started_at", pa.timestamp("us", tz="UTC")),
    ("finished_at", pa.timestamp("us", tz="UTC")),
    ("run_s", pa.float64()),
    ("error", pa.string()),
    ("verified", pa.bool_()),
)
#: Metric columns every report has, whatever its results carry: both protocols, both stages.
STANDARD_METRIC_COLUMNS: tuple[str, ...] = tuple(
    f"{protocol}_{stage}_{label}"
    for protocol in (ALL_FRAMES, PROTOCOL)
    for stage in STAGES
    for label in METRICS.values()
)


def outcome_cells(job: JobRecord) -> dict[str, Any]:
    """The outcome columns of one job (nulls until it SUCCEEDED)."""
    if job.state != JobState.SUCCEEDED:
        return {}
    items = reasons(outcome_of(job.summary))
    first = primary_reason(items) or {}
    return {
        "outcome": job.outcome or outcome_status(job.summary), "reason": first.get("code"),
        "reason_frame": first.get("frame"), "reason_value": first.get("value"), "reason_unit": first.get("unit"),
        "reason_message": first.get("message"), "reasons": ";".join(r["code"] for r in items) or None,
    }  # fmt: skip


def _verified(summary: Mapping[str, Any] | None) -> bool | None:
    metrics = summary.get("metrics") if summary else None
    proof = metrics.get("verification") if isinstance(metrics, Mapping) else None
    verified = proof.get("verified") if isinstance(proof, Mapping) else None
    return verified if isinstance(verified, bool) else None


def report_rows(jobs: list[JobRecord]) -> tuple[list[str], list[dict[str, Any]]]:
    """(metric column names, rows): both protocols' columns first, then any other protocol's."""
    rows: list[dict[str, Any]] = []
    metric_names: dict[str, None] = dict.fromkeys(STANDARD_METRIC_COLUMNS)
    for job in jobs:
        summary = job.summary if job.state == JobState.SUCCEEDED else None
        metrics = report_columns(summary)
        metric_names.update(dict.fromkeys(metrics))
        run_s = (job.finished_at - job.started_at).total_seconds() if job.finished_at and job.started_at else None
        rows.append({
            "job_id": job.id, "name": job.name, **outcome_cells(job), "state": job.state, "attempt": job.attempt,
            "frames": job.num_frames, "created_at": job.created_at, "started_at": job.started_at,
            "finished_at": job.finished_at, "run_s": run_s,
            "error": job.errors[-1].get("error") if job.errors else None, "verified": _verified(summary), **metrics,
        })  # fmt: skip
    standard = set(STANDARD_METRIC_COLUMNS)
    names = [*STANDARD_METRIC_COLUMNS, *sorted(n for n in metric_names if n not in standard)]
    for row in rows:
        for name, _ in BASE_COLUMNS:
            row.setdefault(name, None)
        for name in names:
            row.setdefault(name, None)
    return names, rows


def to_csv(jobs: list[JobRecord]) -> bytes:
    names, rows = report_rows(jobs)
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=[n for n, _ in BASE_COLUMNS] + names, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if v is None else v.isoformat() if hasattr(v, "isoformat") else v)
                         for k, v in row.items()})  # fmt: skip
    return out.getvalue().encode()


def to_parquet(jobs: list[JobRecord]) -> bytes:
    names, rows = report_rows(jobs)
    schema = pa.schema([pa.field(n, t) for n, t in BASE_COLUMNS] + [pa.field(n, pa.float64()) for n in names])
    table = pa.Table.from_pylist(rows, schema=schema)
    sink = io.BytesIO()
    pq.write_table(table, sink)
    return sink.getvalue()
