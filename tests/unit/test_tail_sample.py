"""bench/tail_sample.py: splitting a sample between processes, and pairing each sequence's before and after."""

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
