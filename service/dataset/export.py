"""Write a dataset release (``common.release_format`` gives the layout): each sequence's result file, the contacts
of all sequences and the index as Parquet, the datasheet with its plots, and the checksum manifest, written last.

The release is assembled in ``OUT.partial`` beside the target and renamed into place when complete, so a
half-written folder never looks like a release."""

from __future__ import annotations

import re
import shutil
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from common.errors import ConfigurationError
from common.release_format import (
    CONTACT_COLUMNS,
    CONTACTS_FILE,
    DATASHEET_FILE,
    INDEX_FILE,
    PLOTS_DIR,
    RESULTS_DIR,
    schema,
)
from common.release_manifest import write_manifest
from common.release_tables import contact_table, index_row, index_table
from common.result_format import RESULT_SUFFIX
from service.dataset.datasheet import datasheet, write_plots
from service.dataset.sources import SourceItem

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")
#: Contact rows gathered before they are written as one Parquet row group: memory stays bounded for any dataset.
ROW_GROUP_ROWS = 500_000


class _ContactWriter:
    """contacts.parquet written as it grows, in row groups of about ``ROW_GROUP_ROWS``."""

    def __init__(self, path: Path) -> None:
        self._writer = pq.ParquetWriter(path, schema(CONTACT_COLUMNS))
        self._pending: list[pa.Table] = []
        self.rows = 0

    def add(self, table: pa.Table) -> None:
        self._pending.append(table)
        self.rows += table.num_rows
        if sum(t.num_rows for t in self._pending) >= ROW_GROUP_ROWS:
            self._flush()

    def _flush(self) -> None:
        if self._pending:
            self._writer.write_table(pa.concat_tables(self._pending))
            self._pending = []

    def close(self) -> None:
        self._flush()
        self._writer.close()


@dataclass(frozen=True)
class ExportSummary:
    out: Path
    sequences: int
    with_result: int
    contacts: int
    files: int


def _file_name(name: str, taken: set[str]) -> str:
    """A file-system-safe, unique stem for ``name`` (``-2``, ``-3`` ... after a repeat)."""
    stem = _UNSAFE.sub("_", name).strip("._") or "sequence"
    unique, n = stem, 1
    while unique.lower() in taken:
        n += 1
        unique = f"{stem}-{n}"
    taken.add(unique.lower())
    return unique


def export_release(
    items: Iterable[SourceItem], out: Path, *, title: str, source: str,
    on_item: Callable[[SourceItem], None] | None = None,
) -> ExportSummary:
    """Write the release to ``out`` (which must not exist, or be an empty folder). ``on_item`` sees each sequence as
    it is written (a progress bar)."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigurationError(f"{out} exists and is not an empty folder")
    work = out.with_name(out.name + ".partial")
    if work.exists():
        shutil.rmtree(work)
    (work / RESULTS_DIR).mkdir(parents=True)
    try:
        rows, contacts = _write(items, work, title, source, on_item)
    except BaseException:  # an unreadable result, a lost connection, Ctrl-C: no half-written release is left
        shutil.rmtree(work, ignore_errors=True)
        raise
    files = sum(1 for p in work.rglob("*") if p.is_file())
    if out.exists():
        out.rmdir()
    work.rename(out)
    return ExportSummary(out, len(rows), sum(r["result_file"] is not None for r in rows), contacts, files)


def _write(items: Iterable[SourceItem], work: Path, title: str, source: str,
           on_item: Callable[[SourceItem], None] | None) -> tuple[list[dict[str, Any]], int]:
    """Everything but the final rename; returns the index rows and the number of contacts."""
    rows: list[dict[str, Any]] = []
    contacts_out = _ContactWriter(work / CONTACTS_FILE)
    taken: set[str] = set()
    names: set[str] = set()
    try:
        for item in items:
            stem = _file_name(item.name, taken)
            sequence = item.name if item.name not in names else stem  # sequence names are unique in a release
            names.add(sequence)
            result_file, contacts = None, None
            if item.blob is not None:
                result_file = f"{RESULTS_DIR}/{stem}{RESULT_SUFFIX}"
                (work / result_file).write_bytes(item.blob)
                table = contact_table(sequence, item.blob)
                contacts_out.add(table)
                contacts = table.num_rows
            rows.append(index_row(sequence, item.blob, result_file, item.job, contacts))
            if on_item is not None:
                on_item(item)
    finally:
        contacts_out.close()
    if not rows:
        raise ConfigurationError("nothing to export: no sequences")
    pq.write_table(index_table(rows), work / INDEX_FILE)
    plots = write_plots(rows, work / PLOTS_DIR)
    (work / DATASHEET_FILE).write_text(datasheet(title, source, rows, contacts_out.rows, plots), encoding="utf-8")
    write_manifest(work)
    return rows, contacts_out.rows
