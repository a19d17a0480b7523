"""What the user sees: live progress (a bar on a terminal, a line every so often otherwise) and the closing
summary: outcomes first (executable or not, and why not), then states and mean raw vs refined metrics."""

from __future__ import annotations

import time
from collections import Counter
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from common.batch_metrics import (
    EXECUTABLE,
    NOT_EXECUTABLE,
    OUTCOMES,
    UNKNOWN,
    finite_number,
    primary_reason,
    reasons,
)
from common.job_state import JobState
from common.metrics_table import MEAN_KEYS, metrics_table
from service.submit.manifest import FAILED_STATES, INVALID, PENDING, REJECTED, Entry

_UNIT_SUFFIX = {"E_t": "_cm", "E_r": "_deg", "E_j": "_cm", "E_ft": "_cm"}
STATE_ORDER: tuple[str, ...] = (PENDING, *JobState, REJECTED, INVALID)


def counts(entries: list[Entry]) -> dict[str, int]:
    """Progress counters: submitted (has a job), running, done (succeeded + downloaded if waiting), failed."""
    return {
        "submitted": sum(e.job_id is not None for e in entries),
        "running": sum(e.state == JobState.RUNNING for e in entries),
        "done": sum(e.state == JobState.SUCCEEDED for e in entries),
        "failed": sum(e.state in FAILED_STATES for e in entries),
    }


def make_progress(console: Console) -> Progress:
    # Twice a second is enough for a bar that moves once a job finishes; rich's default redraws 10 times.
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=False,
        refresh_per_second=2,
    )


def describe(entries: list[Entry]) -> str:
    c = counts(entries)
    text = f"submitted {c['submitted']} · running {c['running']} · done {c['done']} · failed {c['failed']}"
    outcomes = Counter(e.outcome for e in entries if e.state == JobState.SUCCEEDED and e.outcome)
    if outcomes.get(NOT_EXECUTABLE):
        text += f" · not executable {outcomes[NOT_EXECUTABLE]}"
    return text


class ProgressLines:
    """Progress where no bar can be drawn (output to a file or a pipe): one line every ``every_s`` seconds,
    and one at the end, so a log shows the run is alive without a line per poll."""

    def __init__(self, console: Console, every_s: float, total: int, clock: Any = time.monotonic) -> None:
        self.console, self.every_s, self.total, self.clock = console, every_s, total, clock
        self.started = clock()
        self.next_at = self.started + every_s
        self.lines = 0

    def update(self, entries: list[Entry], finished: int, force: bool = False) -> None:
        now = self.clock()
        if not force and now < self.next_at:
            return
        self.next_at = now + self.every_s
        self.lines += 1
        elapsed = int(now - self.started)
        self.console.print(f"[{elapsed // 3600}:{elapsed // 60 % 60:02d}:{elapsed % 60:02d}] {finished}/{self.total} "
                           f"finished: {describe(entries)}", highlight=False, soft_wrap=True)  # fmt: skip

    def seconds_to_next(self) -> float:
        return max(0.0, self.next_at - self.clock())


def _metric(stage: Any, key: str) -> float | None:
    if "." in key:  # a nested block: "paper.E_t"
        block, _, key = key.partition(".")
        stage = stage.get(block) if isinstance(stage, dict) else None
    if not isinstance(stage, dict):
        return None
    for name in (key, key + _UNIT_SUFFIX.get(key, "")):
        if name in stage:
            return finite_number(stage[name])
    return None


def metric_means(entries: list[Entry]) -> dict[str, dict[str, float | None]]:
    """Mean of each metric over succeeded entries that have it, for ``raw`` and ``refined``."""
    out: dict[str, dict[str, float | None]] = {}
    for stage in ("raw", "refined"):
        out[stage] = {}
        for key in MEAN_KEYS:
            values = [
                v
                for e in entries
                if e.state == JobState.SUCCEEDED and e.metrics
                for v in [_metric(e.metrics.get(stage), key)]
                if v is not None
            ]
            out[stage][key] = sum(values) / len(values) if values else None
    return out


def outcome_counts(entries: list[Entry]) -> dict[str, int]:
    """Succeeded sequences per outcome (``unknown``: a result without an outcome, or one not polled since)."""
    found = Counter(e.outcome or UNKNOWN for e in entries if e.state == JobState.SUCCEEDED)
    return {name: found.get(name, 0) for name in OUTCOMES}


def summary_document(entries: list[Entry], retried: int = 0) -> dict[str, Any]:
    """The summary as JSON: succeeded sequences per outcome, with each not executable one's reason, jobs per
    state, FAILED jobs requeued by this run (``--retry-failed``) and mean raw / refined metrics over succeeded
    sequences."""
    not_executable = [e for e in entries if e.state == JobState.SUCCEEDED and e.outcome == NOT_EXECUTABLE]
    return {
        "outcomes": outcome_counts(entries),
        "not_executable": [{"label": e.label, "job_id": e.job_id, "reason": e.reason} for e in not_executable],
        "states": dict(sorted(Counter(e.state for e in entries).items())),
        "total": len(entries),
        "retried": retried,
        "succeeded_with_metrics": sum(1 for e in entries if e.state == JobState.SUCCEEDED and e.metrics),
        "mean_metrics": metric_means(entries),
    }


def outcome_table(entries: list[Entry]) -> Table:
    succeeded = sum(e.state == JobState.SUCCEEDED for e in entries)
    table = Table(title=f"Outcome of {succeeded} succeeded sequences (success on the paper's protocol)")
    table.add_column("outcome")
    table.add_column("count", justify="right")
    labels = {EXECUTABLE: "executable", NOT_EXECUTABLE: "not executable", UNKNOWN: "unknown (no outcome in result)"}
    for name, n in outcome_counts(entries).items():
        if n or name != UNKNOWN:
            table.add_row(labels[name], str(n))
    return table


def reason_text(reason: dict[str, Any] | None) -> str:
    if not reason:
        return "no reason given"
    return f"{reason.get('code')}: {reason.get('message') or ''}".rstrip(": ")


def summary_tables(entries: list[Entry]) -> tuple[Table, Table]:
    states = Counter(e.state for e in entries)
    jobs = Table(title="Jobs by state")
    jobs.add_column("state")
    jobs.add_column("count", justify="right")
    for state in sorted(states, key=lambda s: (STATE_ORDER.index(s) if s in STATE_ORDER else 99, s)):
        jobs.add_row(state, str(states[state]))
    jobs.add_row("total", str(len(entries)), style="bold")

    with_metrics = sum(1 for e in entries if e.state == JobState.SUCCEEDED and e.metrics)
    means = metric_means(entries)
    metrics = metrics_table(
        {"raw replay": means["raw"], "refined": means["refined"]},
        title=f"Mean metrics over {with_metrics} succeeded sequences",
    )
    return jobs, metrics


def print_summary(console: Console, entries: list[Entry], retried: int = 0, retry_hint: bool = False) -> None:
    """The outcome first (and why each not executable sequence is not), then the tables and each problem;
    ``retried`` FAILED jobs were requeued by this run. ``retry_hint``: the run had no ``--retry-failed``, so point
    at it when some jobs are FAILED."""
    console.print(outcome_table(entries))
    not_executable = [e for e in entries if e.state == JobState.SUCCEEDED and e.outcome == NOT_EXECUTABLE]
    for e in not_executable[:20]:
        console.print(f"[yellow]not executable[/yellow] {e.label}: {reason_text(e.reason)}", highlight=False)
    if len(not_executable) > 20:
        console.print(f"... and {len(not_executable) - 20} more not executable (see the batch report)")
    jobs, metrics = summary_tables(entries)
    console.print(jobs)
    console.print(metrics)
    if retried:
        console.print(f"retried {retried} FAILED job{'s' if retried != 1 else ''} (same job ids, new attempts)")
    problems = [e for e in entries if e.state in FAILED_STATES or (e.error and e.state == PENDING)]
    for e in problems[:20]:
        console.print(f"[red]{e.state}[/red] {e.label}: {e.error or 'no detail'}", highlight=False)
    if len(problems) > 20:
        console.print(f"... and {len(problems) - 20} more (see the manifest)")
    failed = sum(e.state == JobState.FAILED for e in entries)
    if retry_hint and failed:
        console.print(
            f"{failed} job{'s' if failed != 1 else ''} FAILED on the service: run the same command with "
            "--retry-failed to retry them",
            highlight=False,
        )


def job_error(doc: dict[str, Any]) -> str:
    """The last error of a FAILED/CANCELLED job (``errors`` holds one entry per attempt)."""
    errors = doc.get("errors")
    if isinstance(errors, list) and errors:
        last = errors[-1]
        return str(last.get("error") if isinstance(last, dict) else last)
    return str(doc.get("error") or doc.get("detail") or f"job {str(doc.get('state', 'failed')).lower()}")


def job_outcome(doc: dict[str, Any]) -> tuple[str | None, dict[str, Any] | None]:
    """(outcome status, primary reason) of a job document; (None, None) before it SUCCEEDED."""
    outcome = doc.get("outcome")
    if not isinstance(outcome, dict) or not isinstance(outcome.get("status"), str):
        return (UNKNOWN, None) if doc.get("state") == JobState.SUCCEEDED else (None, None)
    # The job body lists its reasons in the contract's shape (``reasons`` reads them as a result's outcome).
    return outcome["status"], primary_reason(reasons({"executable": False, "reasons": outcome.get("reasons")}))


def job_metrics(doc: dict[str, Any]) -> dict[str, Any] | None:
    for holder in (doc.get("summary"), doc):
        if isinstance(holder, dict) and isinstance(holder.get("metrics"), dict):
            return dict(holder["metrics"])
    return None
