"""Find the sequences under the paths a user names, and load each one as a validated ``Sequence``.

``--format auto`` takes ``*.npz`` and ``*.json`` files, searches folders recursively, and treats a folder that
looks like a DexYCB release (``calibration/`` beside subject folders whose sequences hold ``meta.yml``) as a
DexYCB root, one item per recorded sequence. ``npz`` / ``json`` restrict the file types; ``dexycb`` requires
every path to be such a root. Discovery only lists; loading (and validation) happens per item, so one bad
file is reported and skipped instead of stopping the whole dataset.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from common.errors import UnsupportedFormatError
from common.sequence import Sequence
from common.sequence_io import load_sequence

SourceFormat = Literal["auto", "npz", "json", "dexycb"]
SOURCE_FORMATS: tuple[str, ...] = ("auto", "npz", "json", "dexycb")
SourceKind = Literal["npz", "json", "dexycb"]

_SUFFIX_KIND: dict[str, SourceKind] = {".npz": "npz", ".json": "json"}


@dataclass(frozen=True)
class Source:
    """One sequence to submit: where it is, how to read it, and a file-system-safe label for its outputs."""

    path: Path  # a file, or a DexYCB sequence folder (``<root>/<subject>/<sequence>``)
    kind: SourceKind
    label: str

    @property
    def ident(self) -> str:
        """The manifest's key for this item (absolute path, so it does not depend on the working folder)."""
        return str(self.path)


def is_dexycb_root(folder: Path) -> bool:
    """A DexYCB release: ``calibration/`` plus ``<subject>/<sequence>/meta.yml``."""
    if not (folder / "calibration").is_dir():
        return False
    return any(True for _ in folder.glob("*/*/meta.yml"))


def _dexycb_sequences(root: Path) -> list[Path]:
    return sorted(p.parent for p in root.glob("*/*/meta.yml"))


def _label(path: Path, root: Path | None) -> str:
    rel = path.relative_to(root) if root is not None and path != root else Path(path.name)
    parts = list(rel.parts)
    parts[-1] = Path(parts[-1]).stem if path.is_file() else parts[-1]
    return "__".join(p.replace(os.sep, "_") for p in parts) or path.stem


def _walk(folder: Path, kinds: set[SourceKind], exclude: list[Path]) -> Iterable[tuple[Path, SourceKind]]:
    for dirpath, dirnames, filenames in os.walk(folder):
        here = Path(dirpath)
        # Never descend into the output folder (its manifest and results are not inputs) or hidden folders.
        dirnames[:] = sorted(
            d for d in dirnames if not d.startswith(".") and not any((here / d).resolve() == e for e in exclude)
        )
        if "dexycb" in kinds and here != folder and is_dexycb_root(here):
            dirnames[:] = []
            for seq_dir in _dexycb_sequences(here):
                yield seq_dir, "dexycb"
            continue
        for name in sorted(filenames):
            kind = _SUFFIX_KIND.get(Path(name).suffix.lower())
            if kind in kinds:
                yield here / name, kind


def discover(paths: list[Path], fmt: SourceFormat = "auto", exclude: list[Path] | None = None) -> list[Source]:
    """Every sequence under ``paths`` in a stable order, without duplicates.

    Raises ``UnsupportedFormatError`` for a path that does not exist, a file of the wrong type for ``fmt``, or
    (``fmt == "dexycb"``) a folder that is not a DexYCB root. ``exclude`` lists folders to skip (the output).
    """
    if fmt not in SOURCE_FORMATS:
        raise UnsupportedFormatError(f"--format must be one of {', '.join(SOURCE_FORMATS)}, got {fmt!r}")
    kinds: set[SourceKind] = {"npz", "json", "dexycb"} if fmt == "auto" else {fmt}
    excluded = [e.resolve() for e in exclude or []]
    found: dict[Path, Source] = {}
    for given in paths:
        path = given.resolve()
        if not path.exists():
            raise UnsupportedFormatError(f"{given} does not exist")
        items: list[tuple[Path, SourceKind]]
        root: Path | None = path
        if path.is_file():
            kind = _SUFFIX_KIND.get(path.suffix.lower())
            if kind is None or kind not in kinds:
                raise UnsupportedFormatError(f"{given}: not a {'/'.join(sorted(kinds))} sequence file")
            items, root = [(path, kind)], None
        elif "dexycb" in kinds and is_dexycb_root(path):
            items = [(p, "dexycb") for p in _dexycb_sequences(path)]
        elif fmt == "dexycb":
            raise UnsupportedFormatError(f"{given} is not a DexYCB root (needs calibration/ and */*/meta.yml)")
        else:
            items = list(_walk(path, kinds, excluded))
        for item_path, kind in items:
            if item_path not in found:
                found[item_path] = Source(item_path, kind, _label(item_path, root))
    return _unique_labels(list(found.values()))


def _unique_labels(sources: list[Source]) -> list[Source]:
    """Two paths may share a label (same relative name under two roots): number the later ones."""
    seen: dict[str, int] = {}
    out = []
    for src in sources:
        n = seen.get(src.label, 0)
        seen[src.label] = n + 1
        out.append(src if n == 0 else Source(src.path, src.kind, f"{src.label}~{n}"))
    return out


def load_source(src: Source, max_frames: int | None = None) -> Sequence:
    """Read and validate one item (raises ``HoiRefineError`` subclasses naming what is wrong)."""
    if src.kind == "dexycb":
        from common.dexycb_native import load_dexycb_native  # local: pulls in YAML + SciPy

        return load_dexycb_native(src.path, max_frames=max_frames)
    return load_sequence(src.path, max_frames=max_frames)
