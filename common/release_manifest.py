"""A dataset release's checksum manifest (issue #54 item 4): ``SHA256SUMS`` at the release's root, one line per
file, ``<sha256 hex>  <path relative to the root>`` (the format ``sha256sum -c SHA256SUMS`` reads), sorted by path,
listing every file of the release but the manifest itself.

Written by ``hoi-refine dataset export``; checked by ``hoi-refine verify RELEASE`` (``check_manifest``).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

from common.errors import UnsupportedFormatError

MANIFEST_NAME = "SHA256SUMS"
_CHUNK = 1 << 20


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def release_files(root: Path) -> list[str]:
    """Every file under ``root`` but the manifest, as sorted POSIX paths relative to ``root``."""
    manifest = root / MANIFEST_NAME
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file() and p != manifest)


def write_manifest(root: Path) -> Path:
    """Hash every file under ``root`` into ``root/SHA256SUMS``; returns its path."""
    lines = [f"{file_sha256(root / rel)}  {rel}\n" for rel in release_files(root)]
    out = root / MANIFEST_NAME
    out.write_text("".join(lines), encoding="utf-8")
    return out


def read_manifest(path: Path) -> dict[str, str]:
    """``{relative path: sha256 hex}``; ``UnsupportedFormatError`` naming the line that is not ``HEX  PATH``."""
    out: dict[str, str] = {}
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        digest, sep, rel = line.partition("  ")
        if not sep or len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest) or not rel:
            raise UnsupportedFormatError(f"{path.name} line {number}: not '<sha256>  <path>'")
        out[rel] = digest
    return out


@dataclass
class ManifestCheck:
    """What comparing a release with its manifest found (paths relative to the root)."""

    files: int = 0
    mismatched: list[str] = field(default_factory=list)  # hash differs
    missing: list[str] = field(default_factory=list)  # listed, not on disk
    unlisted: list[str] = field(default_factory=list)  # on disk, not listed

    @property
    def ok(self) -> bool:
        return not (self.mismatched or self.missing or self.unlisted)


def check_manifest(root: Path) -> ManifestCheck | None:
    """Every listed file's SHA-256 against ``root/SHA256SUMS`` and no file left unlisted; None without one."""
    path = root / MANIFEST_NAME
    if not path.is_file():
        return None
    listed = read_manifest(path)
    check = ManifestCheck(files=len(listed))
    for rel, digest in sorted(listed.items()):
        target = root / rel
        if ".." in Path(rel).parts or Path(rel).is_absolute() or not target.is_file():
            check.missing.append(rel)
        elif file_sha256(target) != digest:
            check.mismatched.append(rel)
    check.unlisted = [rel for rel in release_files(root) if rel not in listed]
    return check
