"""A dataset release's format (issue #54 item 4): docs/dataset.md lists the columns the export writes, and the
checksum manifest reads only what it writes and notices every kind of change."""

from __future__ import annotations

from pathlib import Path

import pytest

from common.errors import UnsupportedFormatError
from common.release_manifest import MANIFEST_NAME, check_manifest, read_manifest, write_manifest
from service.dataset.datasheet import columns_markdown

DOCS = Path(__file__).resolve().parents[2] / "docs" / "dataset.md"


def test_the_docs_list_the_columns_the_export_writes() -> None:
    assert "\n".join(columns_markdown()) in DOCS.read_text(encoding="utf-8")


def test_the_manifest_notices_changed_missing_and_unlisted_files(tmp_path: Path) -> None:
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "a.result.npz").write_bytes(b"a")
    (tmp_path / "index.parquet").write_bytes(b"i")
    write_manifest(tmp_path)
    assert set(read_manifest(tmp_path / MANIFEST_NAME)) == {"index.parquet", "results/a.result.npz"}
    check = check_manifest(tmp_path)
    assert check is not None and check.ok and check.files == 2

    (tmp_path / "index.parquet").write_bytes(b"j")
    (tmp_path / "results" / "a.result.npz").unlink()
    (tmp_path / "extra.txt").write_text("x")
    check = check_manifest(tmp_path)
    assert check is not None and not check.ok
    assert (check.mismatched, check.missing, check.unlisted) == (["index.parquet"], ["results/a.result.npz"],
                                                                 ["extra.txt"])
    assert check_manifest(tmp_path / "results") is None  # no manifest: not a release


def test_a_manifest_line_that_is_not_hex_and_path_is_refused_and_no_path_leaves_the_release(tmp_path: Path) -> None:
    (tmp_path / MANIFEST_NAME).write_text("xyz  index.parquet\n")
    with pytest.raises(UnsupportedFormatError, match="line 1"):
        read_manifest(tmp_path / MANIFEST_NAME)
    (tmp_path.parent / "outside").write_bytes(b"o")
    (tmp_path / MANIFEST_NAME).write_text(f"{'0' * 64}  ../outside\n")
    check = check_manifest(tmp_path)
    assert check is not None and check.missing == ["../outside"]
