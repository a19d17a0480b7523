"""One result's rows in the release's tables (``service.dataset.columns``): its index row and its contacts."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any

import numpy as np
import pyarrow as pa

from common.batch_metrics import outcome_status, primary_reason, protocol_sections, reasons
from common.outcome import outcome_of
from common.result_format import CONTACT_KEYS, PART_CONTACT_KEYS, content_digest, read_arrays, read_summary
from service.dataset.columns import (
    CONTACT_COLUMNS,
    INDEX_COLUMNS,
    METRICS,
    PROTOCOLS,
    STAGES,
    VERSIONED,
    metric_column,
    schema,
)

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
