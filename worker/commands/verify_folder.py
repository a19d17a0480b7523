"""``hoi-refine verify DIR`` (issue #54 item 3): every result under a folder or a dataset release, on a process pool
(``worker.verification.folder``), with a progress bar, a summary table and an optional JSON report. A release's
checksum manifest is checked, and its two tables against its result files (``common.release_tables``): a table
rewritten along with its checksum still fails. Exit code 0 when everything passed, 1 when anything failed or
could not be read, 2 for bad input (raised as a project error: no results under the folder, a manifest that cannot
be read)."""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from common.errors import ConfigurationError
from common.release_manifest import MANIFEST_NAME, ManifestCheck, check_manifest
from common.release_tables import TableProblem, check_release_tables
from common.settings import get_settings
from worker.verification import FileVerdict, find_results, verify_files
from worker.verification.folder import STATUSES, Failure, VerifyOptions, default_jobs

#: Longest failure text shown in the table (the JSON report keeps it whole).
_SHOWN = 110
_LOG_WIDTH = 200


def verify_folder(root: Path, *, jobs: int | None, report_path: Path | None, allow_config: bool) -> int:
    paths = find_results(root)
    if not paths:
        raise ConfigurationError(f"no *.result.npz under {root}")
    manifest = check_manifest(root)
    settings = get_settings()
    options = VerifyOptions(allow_config=allow_config, cache_dir=settings.resolved_cache_dir(),
                            mano_dir=settings.mano_dir)
    workers = max(1, jobs if jobs is not None else default_jobs(paths))
    console = Console(stderr=True)
    start = time.perf_counter()
    columns = (TextColumn("verify"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[tally]}"),
               TimeElapsedColumn())
    tally = dict.fromkeys(STATUSES, 0)

    def counted(verdict: FileVerdict) -> str:
        tally[verdict.status] += 1
        return "  ".join(f"{k} {v}" for k, v in tally.items() if v)

    if console.is_terminal:
        with Progress(*columns, console=console, transient=False) as progress:
            task = progress.add_task("verify", total=len(paths), tally="")
            verdicts = verify_files(paths, options, jobs=workers,
                                    on_done=lambda v: progress.update(task, advance=1, tally=counted(v)))
    else:  # a log or a pipe: one line a result, rather than a bar's last frame run into the summary
        def log_line(verdict: FileVerdict) -> None:
            now = counted(verdict)
            console.print(f"verify {sum(tally.values())}/{len(paths)}: {verdict.status} "
                          f"{Path(verdict.path).name} ({now})", soft_wrap=True)

        verdicts = verify_files(paths, options, jobs=workers, on_done=log_line)
    tables = check_release_tables(root)
    for verdict in verdicts:
        verdict.path = Path(verdict.path).relative_to(root).as_posix()
    seconds = time.perf_counter() - start
    all_passed = (all(v.status == "passed" for v in verdicts) and (manifest is None or manifest.ok)
                  and (tables is None or not tables[1]))
    out = Console()
    if not out.is_terminal:  # a log or a pipe: room for the whole failure line rather than rich's 80 columns
        out = Console(width=_LOG_WIDTH)
    table = _table(verdicts, manifest, tables[1] if tables else [])
    if table.row_count:
        out.print(table)
    line = ", ".join(f"{n} {status}" for status, n in _counts(verdicts).items())
    if manifest is not None:
        line += f"; {MANIFEST_NAME}: {manifest.files} files, " + ("all match" if manifest.ok else "MISMATCH")
    if tables is not None:
        line += f"; release tables: {tables[0]} sequences, " + ("match the results" if not tables[1] else
                                                                 f"{len(tables[1])} differences")
    out.print(f"{len(verdicts)} results on {min(workers, len(paths))} processes in {seconds:.1f} s: {line}")
    if report_path is not None:
        report = _report(root, verdicts, manifest, tables, workers, seconds, all_passed)
        report_path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
        out.print(f"report: {report_path}")
    out.print("verify: OK - every result verified" if all_passed else "verify: FAILED - see the table above")
    return 0 if all_passed else 1


def _counts(verdicts: list[FileVerdict]) -> dict[str, int]:
    return {status: sum(v.status == status for v in verdicts) for status in STATUSES}


def _table(verdicts: list[FileVerdict], manifest: ManifestCheck | None, problems: list[TableProblem]) -> Table:
    table = Table(title="verify: what did not pass", show_lines=False)
    for name in ("file", "status", "field", "frame", "what"):
        table.add_column(name, overflow="fold")
    for v in verdicts:
        if v.status == "passed":
            continue
        # The headline: the first failure that names a frame (where to look), else the first.
        first = next((f for f in v.failures if f.frame is not None), v.failures[0] if v.failures else
                     Failure("result", None, ""))
        more = f" (+{len(v.failures) - 1} more)" if len(v.failures) > 1 else ""
        table.add_row(v.path, v.status, first.field, "" if first.frame is None else str(first.frame),
                      _short(first.message) + more)
    if manifest is not None:
        for kind, paths in (("checksum differs", manifest.mismatched), ("listed, missing", manifest.missing),
                            ("not listed", manifest.unlisted)):
            for rel in paths:
                table.add_row(rel, "failed", MANIFEST_NAME, "", kind)
    for p in problems:
        table.add_row(p.file, "failed", p.column, "" if p.frame is None else str(p.frame),
                      _short(f"{p.sequence}: {p.message}" if p.sequence else p.message))
    return table


def _short(text: str) -> str:
    line = text.splitlines()[0] if text else ""
    return line if len(line) <= _SHOWN else line[: _SHOWN - 1] + "…"


def _report(root: Path, verdicts: list[FileVerdict], manifest: ManifestCheck | None,
            tables: tuple[int, list[TableProblem]] | None, jobs: int, seconds: float, all_passed: bool
            ) -> dict[str, Any]:
    return {
        "root": str(root), "all_passed": all_passed, "jobs": jobs, "seconds": round(seconds, 3),
        "counts": _counts(verdicts),
        "manifest": None if manifest is None else {
            "file": MANIFEST_NAME, "files": manifest.files, "ok": manifest.ok, "mismatched": manifest.mismatched,
            "missing": manifest.missing, "unlisted": manifest.unlisted,
        },
        "release_tables": None if tables is None else {
            "sequences": tables[0], "ok": not tables[1], "problems": [asdict(p) for p in tables[1]],
        },
        "files": [v.to_dict() for v in verdicts],
    }  # fmt: skip
