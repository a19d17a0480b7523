"""The server-side batch of a ``hoi-refine submit`` run (issue #20 item 1).

A run submits every sequence into one batch (``POST /v1/batches``), whose id is kept in the manifest so a
re-run adds to, and reports on, the same batch. At the end the batch's own view is printed: counts per state
and the server's aggregate of raw-replay vs refined metrics, over every job of the batch (also those a
different out folder or an earlier run submitted into it).
"""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.table import Table

from common.api_client import ApiClient
from common.errors import ApiError
from common.metrics_table import metrics_table
from service.submit.manifest import Manifest


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


def batch_tables(doc: dict[str, Any]) -> list[Table]:
    """The batch's counts and, per protocol, its mean raw vs refined metrics."""
    counts = Table(title=f"Batch {doc.get('name', '')} ({doc.get('state', '?')}): jobs by state")
    counts.add_column("state")
    counts.add_column("count", justify="right")
    for state, n in (doc.get("counts") or {}).items():
        counts.add_row(state, str(n))
    counts.add_row("total", str(doc.get("total", 0)), style="bold")
    tables = [counts]
    for protocol, stages in (doc.get("metrics") or {}).items():
        raw, refined = stages.get("raw") or {}, stages.get("refined") or {}
        # The aggregate names the success rate SR (``common.batch_metrics``); the table reads it as success.
        columns = {name: {**s, "success": s.get("SR")} for name, s in (("raw replay", raw), ("refined", refined))}
        title = f"Batch metrics ({protocol}), over {refined.get('n', raw.get('n', 0))} succeeded jobs"
        tables.append(metrics_table(columns, title=title))
    return tables


def print_batch(console: Console, client: ApiClient, api_url: str, batch_id: str) -> dict[str, Any] | None:
    """Print the batch's URL and summary; returns the batch document (None when it cannot be read now)."""
    console.print(f"batch: {batch_url(api_url, batch_id)}", highlight=False)
    try:
        doc = client.batch(batch_id)
    except ApiError as exc:
        console.print(f"[yellow]could not read the batch summary: {exc}[/yellow]", highlight=False)
        return None
    for table in batch_tables(doc):
        console.print(table)
    return doc
