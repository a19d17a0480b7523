"""The server-side batch of a ``hoi-refine submit`` run (issue #20 item 1).

A run submits every sequence into one batch (``POST /v1/batches``), whose id is kept in the manifest so a
re-run adds to, and reports on, the same batch. At the end the batch's own view is printed: its URLs, counts per
outcome and per state, and the server's aggregate of raw-replay vs refined metrics, over every job of the batch
(also those a different out folder or an earlier run submitted into it); its per-sequence report is saved as
CSV and Parquet beside the manifest.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from common.api_client import ApiClient
from common.errors import ApiError
from common.metrics_table import metrics_table
from service.submit.manifest import Manifest, write_atomic

#: The batch's report, saved beside the manifest: format -> file name.
REPORT_FILES: dict[str, str] = {"csv": "report.csv", "parquet": "report.parquet"}


def batch_url(api_url: str, batch_id: str) -> str:
    return f"{api_url.rstrip('/')}/v1/batches/{batch_id}"


def ensure_batch(client: ApiClient, manifest: Manifest, api_url: str, name: str, console: Console) -> str | None:
    """The run's batch id: the manifest's when the server still has it, else a new batch (saved in the
    manifest). None when the server has no batches (an older server: jobs are submitted without one)."""
    known = manifest.meta.get("batch_id")
    if known and manifest.meta.get("batch_api") == api_url:
        try:
            client.batch(str(known))
            return str(known)
        except ApiError as exc:
            if exc.status != 404:
                raise
            console.print(f"[yellow]batch {known} is gone from the server; starting a new one[/yellow]")
    try:
        doc = client.create_batch(name, {"source": "hoi-refine submit"})
    except ApiError as exc:
        if exc.status in (404, 405):
            console.print("[yellow]this server has no batches; submitting jobs without one[/yellow]")
            return None
        raise
    manifest.meta.update({"batch_id": doc["id"], "batch_api": api_url})
    manifest.save()
    return str(doc["id"])


def report_url(api_url: str, batch_id: str, fmt: str) -> str:
    return f"{batch_url(api_url, batch_id)}/report?format={fmt}"


def batch_tables(doc: dict[str, Any]) -> list[Table]:
    """The batch's outcomes, counts and, per protocol, its mean raw vs refined metrics."""
    outcomes = Table(title=f"Batch {doc.get('name', '')}: succeeded jobs by outcome")
    outcomes.add_column("outcome")
    outcomes.add_column("count", justify="right")
    for name, n in (doc.get("outcomes") or {}).items():
        outcomes.add_row(name.replace("_", " "), str(n))
    counts = Table(title=f"Batch {doc.get('name', '')} ({doc.get('state', '?')}): jobs by state")
    counts.add_column("state")
    counts.add_column("count", justify="right")
    for state, n in (doc.get("counts") or {}).items():
        counts.add_row(state, str(n))
    counts.add_row("total", str(doc.get("total", 0)), style="bold")
    tables = [outcomes, counts] if doc.get("outcomes") else [counts]
    for protocol, stages in (doc.get("metrics") or {}).items():
        raw, refined = stages.get("raw") or {}, stages.get("refined") or {}
        # The aggregate names the success rate SR (``common.batch_metrics``); the table reads it as success.
        columns = {name: {**s, "success": s.get("SR")} for name, s in (("raw replay", raw), ("refined", refined))}
        title = f"Batch metrics ({protocol}), over {refined.get('n', raw.get('n', 0))} succeeded jobs"
        tables.append(metrics_table(columns, title=title))
    return tables


def print_batch(console: Console, client: ApiClient, api_url: str, batch_id: str) -> dict[str, Any] | None:
    """Print the batch's URLs and summary; returns the batch document (None when it cannot be read now)."""
    console.print(f"batch: {batch_url(api_url, batch_id)}", highlight=False, soft_wrap=True)
    for fmt in REPORT_FILES:
        console.print(f"report ({fmt}): {report_url(api_url, batch_id, fmt)}", highlight=False, soft_wrap=True)
    console.print(f"dashboard: {api_url.rstrip('/')}/ui#/batches/{batch_id}", highlight=False, soft_wrap=True)
    try:
        doc = client.batch(batch_id)
    except ApiError as exc:
        console.print(f"[yellow]could not read the batch summary: {exc}[/yellow]", highlight=False)
        return None
    for table in batch_tables(doc):
        console.print(table)
    return doc


def save_reports(console: Console, client: ApiClient, api_url: str, batch_id: str, out_dir: Path) -> dict[str, str]:
    """Download the batch's report as CSV and Parquet into ``out_dir`` (beside the manifest); returns the files
    written, by format. A report that cannot be read now is reported and skipped (its URL was printed)."""
    saved: dict[str, str] = {}
    for fmt, name in REPORT_FILES.items():
        try:
            blob = client.batch_report(batch_id, fmt)
        except ApiError as exc:
            console.print(f"[yellow]could not save the {fmt} report: {exc}[/yellow]", highlight=False)
            continue
        write_atomic(out_dir / name, blob)
        saved[fmt] = str(out_dir / name)
    if saved:
        console.print(f"saved the batch report: {', '.join(saved.values())}", highlight=False, soft_wrap=True)
    return saved
