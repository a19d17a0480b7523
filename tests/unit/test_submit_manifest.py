"""Bulk submit's manifest: round trip, atomic rewrite, concurrent updates, refusing foreign files."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path

import pytest

from common.errors import UnsupportedFormatError
from service.submit.manifest import MANIFEST_NAME, Manifest


def test_round_trip_keeps_every_field(tmp_path: Path) -> None:
    m = Manifest.load_or_create(tmp_path)
    m.meta["options"] = {"seed": 1}
    e = m.get_or_add("/data/a.npz", "a", "npz")
    m.update(e, key="k1", job_id="j1", state="SUCCEEDED", files={"result": "results/a.result.npz"},
             metrics={"raw": {"E_t": 1.5}}, posts=1)
    assert m.get_or_add("/data/a.npz", "other-label", "npz") is e  # one entry per source

    back = Manifest.load_or_create(tmp_path)
    (b,) = back.snapshot()
    assert (b.key, b.job_id, b.state, b.files, b.metrics, b.posts, b.label) == (
        "k1", "j1", "SUCCEEDED", {"result": "results/a.result.npz"}, {"raw": {"E_t": 1.5}}, 1, "a",
    )  # fmt: skip
    assert back.meta == {"options": {"seed": 1}}


def test_reset_forgets_the_job_but_keeps_the_identity(tmp_path: Path) -> None:
    m = Manifest.load_or_create(tmp_path)
    e = m.get_or_add("/data/a.npz", "a", "npz")
    m.update(e, key="old", job_id="j1", state="FAILED", error="boom", posts=2)
    m.reset(e, "new")
    (b,) = Manifest.load_or_create(tmp_path).snapshot()
    assert (b.source, b.label, b.key, b.job_id, b.state, b.error, b.posts) == (
        "/data/a.npz", "a", "new", None, "PENDING", None, 0,
    )  # fmt: skip


def test_a_failed_write_leaves_the_previous_manifest_intact(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    m = Manifest.load_or_create(tmp_path)
    e = m.get_or_add("/data/a.npz", "a", "npz")
    m.update(e, job_id="j1")
    before = (tmp_path / MANIFEST_NAME).read_text()

    def crash(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError, match="disk full"):
        m.update(e, job_id="j2")
    monkeypatch.undo()
    assert (tmp_path / MANIFEST_NAME).read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [MANIFEST_NAME]  # no temporary left behind


def test_concurrent_updates_all_land(tmp_path: Path) -> None:
    m = Manifest.load_or_create(tmp_path)
    entries = [m.get_or_add(f"/data/{i}.npz", str(i), "npz") for i in range(16)]

    def work(i: int) -> None:
        for n in range(5):
            m.update(entries[i], posts=n + 1, job_id=f"j{i}")

    threads = [threading.Thread(target=work, args=(i,)) for i in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    back = {e.source: e for e in Manifest.load_or_create(tmp_path).snapshot()}
    assert all(back[f"/data/{i}.npz"].job_id == f"j{i}" and back[f"/data/{i}.npz"].posts == 5 for i in range(16))


def test_refuses_files_that_are_not_manifests(tmp_path: Path) -> None:
    (tmp_path / MANIFEST_NAME).write_text("{not json")
    with pytest.raises(UnsupportedFormatError, match="not valid JSON"):
        Manifest.load_or_create(tmp_path)
    (tmp_path / MANIFEST_NAME).write_text(json.dumps({"entries": []}))
    with pytest.raises(UnsupportedFormatError, match="not a hoi-refine submit manifest"):
        Manifest.load_or_create(tmp_path)
