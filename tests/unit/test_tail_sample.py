"""bench/tail_sample.py: splitting a sample between processes, pairing each sequence's before and after, and
carrying a run over to another day through the archive."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

import bench.tail_sample as tail_sample


def _write(cache: Path, stem: str, mode: str, wall: float, *, first_ok: bool, cut: bool = False) -> None:
    reasons = [{"code": "plan_cut_short"}] if cut else []
    row: dict[str, Any] = {"sequence": stem, "mode": mode, "wall_s": wall, "attempts": 1 if cut else 4,
                           "success": first_ok, "E_t": 0.5, "E_r": 2.0, "first_attempt_success": first_ok,
                           "outcome": {"reasons": reasons}}
    (cache / f"{stem}.{mode}.json").write_text(json.dumps(row))


@pytest.fixture(autouse=True)
def _own_archive(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tail_sample, "ARCHIVE", tmp_path / "archive" / "runs.jsonl")
    (tmp_path / "archive").mkdir()


def test_shards_split_a_sample_without_overlap() -> None:
    stems = [f"s{i}" for i in range(7)]
    parts = [tail_sample.shard(stems, f"{k}/3") for k in range(3)]
    assert sorted(s for p in parts for s in p) == stems
    with pytest.raises(SystemExit):
        tail_sample.shard(stems, "3/3")


def test_after_is_the_bounded_run_only_where_it_was_cut(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tail_sample, "CACHE", tmp_path)
    _write(tmp_path, "ok", "full", 30.0, first_ok=True)
    _write(tmp_path, "cut", "full", 700.0, first_ok=False)
    _write(tmp_path, "cut", "bounded", 40.0, first_ok=False, cut=True)
    _write(tmp_path, "same", "full", 200.0, first_ok=False)
    _write(tmp_path, "same", "bounded", 210.0, first_ok=False)
    _write(tmp_path, "pending", "full", 300.0, first_ok=False)  # its bounded run has not come yet

    got = {before["sequence"]: (before["wall_s"], after["wall_s"])
           for before, after in tail_sample.pairs(["ok", "cut", "same", "pending", "missing"])}

    assert got == {"ok": (30.0, 30.0), "cut": (700.0, 40.0), "same": (200.0, 200.0)}


def test_report_counts_the_cut_sequences(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tail_sample, "CACHE", tmp_path)
    monkeypatch.setattr(tail_sample, "sample_stems", lambda name: ["ok", "cut"] if name == "dev120" else [])
    _write(tmp_path, "ok", "full", 30.0, first_ok=True)
    _write(tmp_path, "cut", "full", 700.0, first_ok=False)
    _write(tmp_path, "cut", "bounded", 40.0, first_ok=False, cut=True)

    text = tail_sample.report(["dev120", "holdout80"])

    assert "| dev120 | 2 | bounded (after) | 1 |" in text
    assert "| cut | 700.0 / 4 / 0.50 / 2.00 | 40.0 / 1 / 0.50 / 2.00 |" in text
    assert "| 700.0 |" in text  # the whole plan's maximum


def test_archived_rows_pair_and_are_not_run_again_once_the_cache_is_gone(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cache = tmp_path / "cache"
    cache.mkdir()
    monkeypatch.setattr(tail_sample, "CACHE", cache)
    _write(cache, "ok", "full", 30.0, first_ok=True)
    _write(cache, "cut", "full", 700.0, first_ok=False)
    _write(cache, "cut", "bounded", 40.0, first_ok=False, cut=True)
    _write(cache, "pending", "full", 300.0, first_ok=False)

    assert tail_sample.archive(["ok", "cut", "pending"]) == 4
    assert tail_sample.archive(["ok", "cut", "pending"]) == 0  # nothing twice
    for file in cache.iterdir():
        file.unlink()  # another machine: var/ is gone
    ran: list[tuple[str, str]] = []

    def run_one(stem: str, mode: str) -> dict[str, Any]:
        ran.append((stem, mode))
        return {"wall_s": 1.0, "attempts": 1, "first_attempt_success": False, "outcome": {"reasons": []}}

    monkeypatch.setattr(tail_sample, "run_one", run_one)

    tail_sample.run(["ok", "cut", "pending"])
    got = {b["sequence"]: (b["wall_s"], a["wall_s"], b["cpu"]) for b, a in tail_sample.pairs(["ok", "cut"])}

    assert ran == [("pending", "full"), ("pending", "bounded")]  # only what the archive lacks
    assert got["cut"][:2] == (700.0, 40.0) and got["ok"][:2] == (30.0, 30.0)
    assert got["ok"][2] == f"{tail_sample.cpu_model()} ({tail_sample.numpy_simd()})"
