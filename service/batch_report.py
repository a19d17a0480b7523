"""The per-sequence report of a batch as CSV or Parquet (issue #20 item 1).

One row per job, oldest first: identity, state, timing, the last error, and the raw / refined metrics of
every protocol the result summaries carry (``common.batch_metrics.report_columns``: ``all_frames_raw_E_t``
...). Columns are the same for every row (a job without a result has nulls), so the file loads as a table.
"""

from __future__ import annotations

import csv
import io
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from common.batch_metrics import ALL_FRAMES, report_columns
from common.job_state import JobState
from common.queue_types import JobRecord

BASE_COLUMNS: tuple[tuple[str, pa.DataType], ...] = (
    ("job_id", pa.string()),
    ("name", pa.string()),
    ("state", pa.string()),
    ("attempt", pa.int64()),
    ("frames", pa.int64()),
    ("created_at", pa.timestamp("us", tz="UTC")),
    ("started_at", pa.timestamp("us", tz="UTC")),
    ("finished_at", pa.timestamp("us", tz="UTC")),
    ("run_s", pa.float64()),
    ("error", pa.string()),
)


def report_rows(jobs: list[JobRecord]) -> tuple[list[str], list[dict[str, Any]]]:
    """(metric column names, rows); metric columns of the all-frames protocol come first."""
    rows: list[dict[str, Any]] = []
    metric_names: dict[str, None] = {}
    for job in jobs:
        metrics = report_columns(job.summary if job.state == JobState.SUCCEEDED else None)
        metric_names.update(dict.fromkeys(metrics))
        run_s = (job.finished_at - job.started_at).total_seconds() if job.finished_at and job.started_at else None
        rows.append({
            "job_id": job.id, "name": job.name, "state": job.state, "attempt": job.attempt,
            "frames": job.num_frames, "created_at": job.created_at, "started_at": job.started_at,
            "finished_at": job.finished_at, "run_s": run_s,
            "error": job.errors[-1].get("error") if job.errors else None, **metrics,
        })  # fmt: skip
    names = sorted(metric_names, key=lambda n: (not n.startswith(ALL_FRAMES + "_"), n))
    for row in rows:
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
