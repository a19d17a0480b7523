"""One result's rows in a release's tables (``common.release_format``): its index row and its contacts; and the
check that a release's tables say what its result files say (``check_release_tables``, run by ``hoi-refine verify``)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from common.batch_metrics import outcome_status, primary_reason, protocol_sections, reasons
from common.outcome import outcome_of
from common.release_format import (
    CONTACT_COLUMNS,
    CONTACTS_FILE,
    INDEX_COLUMNS,
    INDEX_FILE,
    METRICS,
    PROTOCOLS,
    STAGES,
    VERSIONED,
    metric_column,
    schema,
)
from common.result_format import CONTACT_KEYS, PART_CONTACT_KEYS, content_digest, read_arrays, read_summary

#: A result's contact array -> its columns in contacts.parquet (vectors become _x, _y, _z).
_VECTORS = {"contact_pos_world": "world", "contact_pos_object": "object", "contact_normal": "normal",
            "contact_force": "force", "contact_torque": "torque"}


def contact_table(sequence: str, blob: bytes) -> pa.Table:
    """The result's contacts as CONTACT_COLUMNS rows, in the order stored (frame order)."""
    arrays = read_arrays(blob)
    missing = [k for k in CONTACT_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"{sequence}: the result has no {', '.join(missing)}")
    n = len(arrays["contact_frame"])
    parts = arrays.get(PART_CONTACT_KEYS[0])
    cols: dict[str, Any] = {
        "sequence": [sequence] * n,
        "frame": np.asarray(arrays["contact_frame"], dtype=np.int32),
        "hand": [str(v) for v in arrays["contact_hand"]],
        "body": [str(v) for v in arrays["contact_body"]],
        "part": [str(v) for v in parts] if parts is not None else [None] * n,
        "depth": np.asarray(arrays["contact_depth"], dtype=np.float64),
    }
    for key, prefix in _VECTORS.items():
        vec = np.asarray(arrays[key], dtype=np.float64).reshape(n, 3)
        for i, axis in enumerate("xyz"):
            cols[f"{prefix}_{axis}"] = vec[:, i]
    return pa.table({c.name: cols[c.name] for c in CONTACT_COLUMNS}, schema=schema(CONTACT_COLUMNS))


def _number(value: Any) -> Any:
    """A JSON figure as stored (None for NaN: Parquet's null, which pandas reads as NaN too)."""
    if isinstance(value, float) and value != value:
        return None
    return value


def metric_cells(summary: Mapping[str, Any]) -> dict[str, Any]:
    sections = protocol_sections(summary)
    row: dict[str, Any] = {}
    for protocol in PROTOCOLS:
        section = sections.get(protocol) or {}
        for stage in STAGES:
            block = section.get(stage)
            for key, (kind, _, _) in METRICS.items():
                value = block.get(key) if isinstance(block, Mapping) else None
                if pa.types.is_boolean(kind):
                    value = value if isinstance(value, bool) else None
                elif isinstance(value, bool) or not isinstance(value, (int, float)):
                    value = None
                row[metric_column(protocol, stage, key)] = _number(value)
    return row


def outcome_cells(summary: Mapping[str, Any]) -> dict[str, Any]:
    outcome = outcome_of(dict(summary))
    items = reasons(outcome.model_dump(mode="json") if outcome is not None else None)
    first = primary_reason(items) or {}
    return {
        "outcome": outcome_status({"outcome": outcome.model_dump(mode="json")} if outcome is not None else None),
        "executable": outcome.executable if outcome is not None else None,
        "reason": first.get("code"), "reason_frame": first.get("frame"), "reason_value": first.get("value"),
        "reason_unit": first.get("unit"), "reason_message": first.get("message"),
        "reasons": ";".join(r["code"] for r in items) or None,
    }  # fmt: skip


def _json(value: Any) -> str | None:
    return None if value is None else json.dumps(value, sort_keys=True)


def index_row(sequence: str, blob: bytes | None, result_file: str | None, job: Mapping[str, Any] | None,
              contacts: int | None) -> dict[str, Any]:
    """One INDEX_COLUMNS row: from the result file when there is one, from the job document (a batch's job
    without a result) otherwise."""
    row: dict[str, Any] = dict.fromkeys(c.name for c in INDEX_COLUMNS)
    row.update(sequence=sequence, result_file=result_file, contacts=contacts)
    if job is not None:
        errors = job.get("errors") or []
        row.update(job_id=job.get("id"), job_state=job.get("state"),
                   job_error=errors[-1].get("error") if errors and isinstance(errors[-1], Mapping) else None)
        proof = ((job.get("summary") or {}).get("metrics") or {}).get("verification")
        if isinstance(proof, Mapping):
            row.update(worker_verified=proof.get("verified"), checked_sha256=proof.get("checked_sha256"))
    if blob is None:
        return row
    summary = read_summary(blob)
    versions = summary.get("versions") or {}
    config = summary.get("config") or {}
    obj = summary.get("object")
    row.update(
        frames=summary.get("frames"), fps=summary.get("fps"), seed=summary.get("seed"),
        object=obj.get("name") if isinstance(obj, Mapping) else _object_name(blob),
        hands=",".join(summary.get("sides") or []) or None,
        file_sha256=hashlib.sha256(blob).hexdigest(), content_sha256=content_digest(blob),
        cpu=versions.get("cpu"), numpy_simd=versions.get("numpy_simd"),
        versions_json=_json(versions), physics_json=_json(config.get("sim")), config_json=_json(config),
        options_json=_json(summary.get("options")),
        **{f"version_{name.replace('-', '_')}": versions.get(name) for name in VERSIONED},
        **outcome_cells(summary), **metric_cells(summary),
    )  # fmt: skip
    return row


def _object_name(blob: bytes) -> str | None:
    """The object's name from the embedded sequence (the summary does not record it)."""
    from common.sequence_io import sequence_from_npz_bytes

    arrays = read_arrays(blob)
    if "sequence_npz" not in arrays:
        return None
    try:
        return sequence_from_npz_bytes(arrays["sequence_npz"].tobytes()).object.name
    except Exception:  # an unreadable embedded sequence leaves the name unknown; verify says why
        return None


def index_table(rows: list[dict[str, Any]]) -> pa.Table:
    return pa.Table.from_pylist(rows, schema=schema(INDEX_COLUMNS))


# ---------------------------------------------------------------------------------------------- checking a release
#: Index columns that come from the job (through the API), not from the result file: a release cannot re-derive them.
JOB_COLUMNS: frozenset[str] = frozenset({"job_id", "job_state", "job_error", "worker_verified", "checked_sha256"})


@dataclass(frozen=True)
class TableProblem:
    """A release table that does not say what its result files say: the table, the sequence, the column, the
    contact's frame (contacts.parquet) and what differs."""

    file: str
    sequence: str | None
    column: str
    frame: int | None
    message: str


def check_release_tables(root: Path) -> tuple[int, list[TableProblem]] | None:
    """Rebuild ``index.parquet`` and ``contacts.parquet`` from the release's result files and compare, cell by cell
    (the job columns aside): (sequences checked, problems); None when ``root`` holds no index (not a release).
    The contacts of the index's sequences lie in index order, each sequence's rows together (as the export writes
    them), so each sequence's rows are a slice and the check is linear in the table's size."""
    if not (root / INDEX_FILE).is_file():
        return None
    try:
        index = pq.read_table(root / INDEX_FILE)
        contacts = pq.read_table(root / CONTACTS_FILE)
    except (OSError, pa.ArrowException) as exc:
        return 0, [TableProblem(INDEX_FILE, None, "file", None, f"the release's tables cannot be read: {exc}")]
    problems: list[TableProblem] = []
    for name, table, columns in ((INDEX_FILE, index, INDEX_COLUMNS), (CONTACTS_FILE, contacts, CONTACT_COLUMNS)):
        if table.schema.names != [c.name for c in columns]:
            problems.append(TableProblem(name, None, "columns", None, "not the release's columns"))
    if problems:
        return 0, problems
    rows = index.to_pylist()
    offset, checked = 0, 0
    for row in rows:
        sequence, result_file = str(row["sequence"]), row["result_file"]
        if result_file is None:
            continue
        path = root / str(result_file)
        if ".." in Path(str(result_file)).parts or not path.is_file():
            problems.append(TableProblem(INDEX_FILE, sequence, "result_file", None, f"{result_file} is missing"))
            continue
        blob = path.read_bytes()
        try:
            expected_contacts = contact_table(sequence, blob)
            expected = index_row(sequence, blob, str(result_file), None, expected_contacts.num_rows)
        except Exception:  # an unreadable result file: verify reports the file itself
            continue
        checked += 1
        for column, value in expected.items():
            if column not in JOB_COLUMNS and not _same(row[column], value):
                problems.append(TableProblem(INDEX_FILE, sequence, column, None,
                                             f"{row[column]!r} in the table, {value!r} in the result file"))
        stored = contacts.slice(offset, expected_contacts.num_rows)
        offset += expected_contacts.num_rows
        problems += _contact_differences(sequence, stored, expected_contacts)
    if offset != contacts.num_rows:
        problems.append(TableProblem(CONTACTS_FILE, None, "rows", None,
                                     f"{contacts.num_rows} rows, the result files give {offset}"))
    return checked, problems


def _same(stored: Any, expected: Any) -> bool:
    if isinstance(stored, float) and isinstance(expected, float):
        return stored == expected or (stored != stored and expected != expected)
    return bool(stored == expected)


def _contact_differences(sequence: str, stored: pa.Table, expected: pa.Table) -> list[TableProblem]:
    """The first differing row of each column of one sequence's contacts."""
    out = []
    frames = expected.column("frame").to_pylist()
    for name in expected.schema.names:
        have, want = stored.column(name).to_pylist(), expected.column(name).to_pylist()
        if len(have) != len(want):
            return [TableProblem(CONTACTS_FILE, sequence, "rows", None,
                                 f"{len(have)} rows where the result file has {len(want)}")]
        row = next((i for i, (a, b) in enumerate(zip(have, want, strict=True)) if not _same(a, b)), None)
        if row is not None:
            out.append(TableProblem(CONTACTS_FILE, sequence, name, frames[row],
                                    f"{have[row]!r} in the table, {want[row]!r} in the result file"))
    return out
