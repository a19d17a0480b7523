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
    RESULT_SUFFIX,
    RESULTS_DIR,
    schema,
)
from common.release_manifest import write_manifest
from common.release_tables import contact_table, index_row, index_table
from service.dataset.datasheet import datasheet, write_plots
from service.dataset.sources import SourceItem

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


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
    rows: list[dict[str, Any]] = []
    contact_parts: list[pa.Table] = []
    taken: set[str] = set()
    names: set[str] = set()
    for item in items:
        stem = _file_name(item.name, taken)
        sequence = item.name if item.name not in names else stem  # sequence names are unique in a release
        names.add(sequence)
        result_file = None
        contacts = None
        if item.blob is not None:
            result_file = f"{RESULTS_DIR}/{stem}{RESULT_SUFFIX}"
            (work / result_file).write_bytes(item.blob)
            table = contact_table(sequence, item.blob)
            contact_parts.append(table)
            contacts = table.num_rows
        rows.append(index_row(sequence, item.blob, result_file, item.job, contacts))
        if on_item is not None:
            on_item(item)
    if not rows:
        shutil.rmtree(work)
        raise ConfigurationError("nothing to export: no sequences")
    contacts_table = pa.concat_tables(contact_parts) if contact_parts else schema(CONTACT_COLUMNS).empty_table()
    pq.write_table(contacts_table, work / CONTACTS_FILE)
    pq.write_table(index_table(rows), work / INDEX_FILE)
    plots = write_plots(rows, work / PLOTS_DIR)
    (work / DATASHEET_FILE).write_text(datasheet(title, source, rows, contacts_table.num_rows, plots),
                                       encoding="utf-8")
    write_manifest(work)
    files = sum(1 for p in work.rglob("*") if p.is_file())
    if out.exists():
        out.rmdir()
    work.rename(out)
    return ExportSummary(out, len(rows), sum(r["result_file"] is not None for r in rows), contacts_table.num_rows,
                         files)
