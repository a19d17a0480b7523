"""The bulk-submission manifest: ``<out>/manifest.json``, what was sent, what came back, what is on disk.

One entry per input (keyed by its absolute path): the Idempotency-Key, the job id, the last known state and
the files downloaded. It is rewritten atomically (temporary file, fsync, rename) after every change, so a
crash or Ctrl-C leaves either the old or the new version, never half a file. A re-run reads it back: items
already downloaded are skipped, submitted ones are polled again instead of being sent a second time.
"""

from __future__ import annotations

import json
import os
import tempfile
import threading
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from common.errors import UnsupportedFormatError
from common.job_state import JobState

MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = "hoi-refine-submit-manifest"
MANIFEST_VERSION = 1

#: An entry's state is a ``JobState`` of the service or one of the tool's own: PENDING (not yet accepted by the
#: server), INVALID (failed local validation, never sent) and REJECTED (the server refused it with a 4xx).
PENDING, INVALID, REJECTED = "PENDING", "INVALID", "REJECTED"
#: Entries the server will never run as they stand: a re-run sends them again once the input changes.
NOT_SENT = frozenset({INVALID, REJECTED})
#: Jobs that ended without a result.
UNSUCCESSFUL = frozenset({JobState.FAILED, JobState.CANCELLED})
#: Entries that failed, whether here or on the server.
FAILED_STATES = UNSUCCESSFUL | NOT_SENT


@dataclass
class Entry:
    source: str
    label: str
    kind: str
    key: str | None = None
    sequence: str | None = None
    job_id: str | None = None
    state: str = PENDING
    attempt: int | None = None
    error: str | None = None
    #: Downloaded files, relative to the output folder: ``result`` and ``contacts``.
    files: dict[str, str] = field(default_factory=dict)
    #: ``{"raw": {...}, "refined": {...}}`` from the result summary.
    metrics: dict[str, Any] | None = None
    #: Once SUCCEEDED: ``executable``, ``not_executable`` or ``unknown`` (a result without an outcome), and the
    #: outcome's primary reason (code, frame, value, unit, message) when it has one.
    outcome: str | None = None
    reason: dict[str, Any] | None = None
    #: POSTs this tool made for the entry (the server dedupes by key; this is for the record).
    posts: int = 0
    #: Times ``--retry-failed`` requeued the FAILED job (``POST /v1/jobs/{id}:retry``; same job id).
    retries: int = 0
    #: Sizes + mtimes of the input and the options when it was submitted (re-runs skip unchanged inputs).
    fingerprint: str | None = None


class Manifest:
    """Thread-safe, atomically saved set of entries (worker threads call ``update``)."""

    def __init__(self, path: Path, meta: dict[str, Any] | None = None) -> None:
        self.path = path
        self.meta: dict[str, Any] = dict(meta or {})
        self.entries: dict[str, Entry] = {}
        self._lock = threading.RLock()

    # ------------------------------------------------------------------ persistence
    @classmethod
    def load_or_create(cls, out_dir: Path) -> Manifest:
        path = out_dir / MANIFEST_NAME
        manifest = cls(path)
        if not path.exists():
            return manifest
        try:
            doc = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise UnsupportedFormatError(f"{path} is not valid JSON ({exc}); move it away to start afresh") from exc
        if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT:
            raise UnsupportedFormatError(f"{path} is not a hoi-refine submit manifest")
        if doc.get("version") != MANIFEST_VERSION:
            raise UnsupportedFormatError(f"{path}: manifest version {doc.get('version')} is not {MANIFEST_VERSION}")
        known = {f.name for f in fields(Entry)}
        manifest.meta = dict(doc.get("meta") or {})
        for raw in doc.get("entries", []):
            entry = Entry(**{k: v for k, v in raw.items() if k in known})
            manifest.entries[entry.source] = entry
        return manifest

    def save(self) -> None:
        with self._lock:
            doc = {
                "format": MANIFEST_FORMAT,
                "version": MANIFEST_VERSION,
                "meta": self.meta,
                "entries": [asdict(e) for e in self.entries.values()],
            }
            text = json.dumps(doc, indent=1, sort_keys=True)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(self.path, text.encode())

    # ------------------------------------------------------------------ entries
    def get_or_add(self, source: str, label: str, kind: str) -> Entry:
        with self._lock:
            entry = self.entries.get(source)
            if entry is None:
                entry = self.entries[source] = Entry(source=source, label=label, kind=kind)
            return entry

    def update(self, entry: Entry, **changes: Any) -> None:
        """Apply ``changes`` to ``entry`` and save, as one step under the lock."""
        with self._lock:
            for name, value in changes.items():
                if not hasattr(entry, name):
                    raise AttributeError(f"manifest entries have no field {name!r}")
                setattr(entry, name, value)
            self.save()

    def reset(self, entry: Entry, key: str) -> None:
        """The input or options changed since the entry was written: forget the old job, keep the identity."""
        with self._lock:
            fresh = Entry(source=entry.source, label=entry.label, kind=entry.kind, key=key)
            for f in fields(Entry):
                setattr(entry, f.name, getattr(fresh, f.name))
            self.save()

    def snapshot(self) -> list[Entry]:
        with self._lock:
            return list(self.entries.values())


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old or the new file, never a partial one."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
