"""Where a release's results come from: a folder of result files, or a batch's jobs through the API."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.api_client import ApiClient
from common.errors import ConfigurationError, UnsupportedFormatError
from common.job_state import FINISHED, JobState
from common.result_format import RESULT_SUFFIX, read_summary


@dataclass(frozen=True)
class SourceItem:
    """One sequence: its name, its result file's bytes (None: a job that has no result) and, from a batch, the
    job document (state, errors, the worker's verification)."""

    name: str
    blob: bytes | None
    job: dict[str, Any] | None = None


def folder_items(root: Path) -> Iterator[SourceItem]:
    """Every ``*.result.npz`` under ``root`` (recursively, sorted), named by the sequence its summary names;
    ``UnsupportedFormatError`` for a file that is not a readable result (a release holds only readable ones)."""
    paths = sorted(p for p in root.rglob(f"*{RESULT_SUFFIX}") if p.is_file())
    if not paths:
        raise ConfigurationError(f"no *{RESULT_SUFFIX} under {root}")
    for path in paths:
        blob = path.read_bytes()
        try:
            summary = read_summary(blob)
        except UnsupportedFormatError as exc:
            raise UnsupportedFormatError(f"{path}: {exc} (`hoi-refine verify` checks a folder)") from exc
        yield SourceItem(str(summary.get("sequence") or path.name[: -len(RESULT_SUFFIX)]), blob)


def batch_jobs(client: ApiClient, batch_id: str) -> list[dict[str, Any]]:
    """Every job of the batch, oldest first; ``ConfigurationError`` while any is still QUEUED or RUNNING."""
    batch = client.batch(batch_id)
    jobs = client.jobs(batch_id=batch_id)
    unfinished = [j["id"] for j in jobs if j.get("state") not in FINISHED]
    if unfinished:
        raise ConfigurationError(f"batch {batch.get('name') or batch_id} has {len(unfinished)} unfinished jobs "
                                 f"(state {batch.get('state')}): export it once they are done")
    return sorted(jobs, key=lambda j: (str(j.get("created_at")), str(j["id"])))


def batch_items(client: ApiClient, jobs: list[dict[str, Any]]) -> Iterator[SourceItem]:
    """Each job's result (downloaded) and full document (the listing leaves out the summary, which holds the
    worker's verification); a job that did not succeed comes without a result."""
    for listed in jobs:
        job, _ = client.job(listed["id"])
        blob = client.result(job["id"]) if job.get("state") == JobState.SUCCEEDED else None
        yield SourceItem(str(job.get("name") or job["id"]), blob, job)
