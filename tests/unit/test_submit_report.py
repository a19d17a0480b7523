"""Bulk submit's closing summary (the outcome first, counts per state, mean raw vs refined metrics) and its
progress lines where no bar can be drawn."""

from __future__ import annotations

import io

import pytest
from rich.console import Console

from service.submit.manifest import Entry
from service.submit.report import (
    ProgressLines,
    counts,
    job_outcome,
    metric_means,
    print_summary,
    summary_document,
)


def _entries() -> list[Entry]:
    ok = {"raw": {"E_t": 4.0, "E_r": 20.0, "success": False}, "refined": {"E_t": 1.0, "success": True}}
    # An older result spelled the keys with units: read the same.
    ok2 = {"raw": {"E_t_cm": 2.0, "E_r_deg": 10.0, "success": True}, "refined": {"E_t_cm": 3.0, "success": True}}
    return [
        Entry("/a", "a", "npz", job_id="1", state="SUCCEEDED", metrics=ok),
        Entry("/b", "b", "npz", job_id="2", state="SUCCEEDED", metrics=ok2),
        Entry("/c", "c", "npz", job_id="3", state="RUNNING"),
        Entry("/d", "d", "npz", job_id="4", state="FAILED", error="worker crashed", metrics={"raw": {"E_t": 99}}),
        Entry("/e", "e", "json", state="INVALID", error="hands: at least one hand is required"),
    ]


def test_means_use_succeeded_jobs_only() -> None:
    means = metric_means(_entries())
    assert means["raw"]["E_t"] == 3.0 and means["raw"]["E_r"] == 15.0 and means["raw"]["success"] == 0.5
    assert means["refined"]["E_t"] == 2.0 and means["refined"]["success"] == 1.0
    assert means["refined"]["E_r"] is None  # no job reported it
    assert counts(_entries()) == {"submitted": 4, "running": 1, "done": 2, "failed": 2}


def test_summary_names_states_metrics_and_problems() -> None:
    out = io.StringIO()
    print_summary(Console(file=out, width=120), _entries())
    text = out.getvalue()
    for expected in ("SUCCEEDED", "RUNNING", "FAILED", "INVALID", "position error E_t", "3.00", "2.00", "50%", "100%",
                     "worker crashed", "at least one hand is required", "over 2 succeeded"):
        assert expected in text, expected


def test_the_summary_puts_the_outcome_first_with_each_reason() -> None:
    reason = {"code": "recording_too_fast", "frame": 12, "value": 41.0, "unit": "deg/frame",
              "message": "the recorded object turns 41 deg between frames 11 and 12"}  # fmt: skip
    entries = [*_entries(), Entry("/f", "f", "npz", job_id="5", state="SUCCEEDED", outcome="not_executable",
                                  reason=reason)]  # fmt: skip
    entries[0].outcome = "executable"
    out = io.StringIO()
    print_summary(Console(file=out, width=120), entries)
    text = out.getvalue()
    assert text.index("Outcome of 3 succeeded sequences") < text.index("Jobs by state")
    assert "not executable f: recording_too_fast: the recorded object turns 41 deg between frames 11 and 12" in text
    assert "unknown (no outcome in result)" in text  # b has no outcome: polled before outcomes existed
    doc = summary_document(entries)
    assert doc["outcomes"] == {"executable": 1, "not_executable": 1, "unknown": 1}
    assert doc["not_executable"] == [{"label": "f", "job_id": "5", "reason": reason}]
    assert next(iter(doc)) == "outcomes"


def test_job_outcome_reads_the_job_body() -> None:
    reasons = [{"code": "rescued_on_finer_parts", "frame": None, "value": None, "unit": None, "message": "kept"},
               {"code": "slipped", "frame": 30, "value": 3.4, "unit": "cm", "message": "slips at frame 30"}]
    body = {"state": "SUCCEEDED", "outcome": {"status": "not_executable", "reasons": reasons}}
    assert job_outcome(body) == ("not_executable", reasons[1])  # the reason that explains the failure
    assert job_outcome({"state": "SUCCEEDED", "outcome": None}) == ("unknown", None)
    assert job_outcome({"state": "RUNNING", "outcome": None}) == (None, None)


def test_progress_lines_come_every_so_often_not_on_every_poll() -> None:
    now = [100.0]
    out = io.StringIO()
    lines = ProgressLines(Console(file=out, width=200), every_s=30.0, total=5, clock=lambda: now[0])
    entries = _entries()
    for t in range(0, 95, 1):  # a poll a second for 95 s
        now[0] = 100.0 + t
        lines.update(entries, finished=2)
    assert lines.lines == 3  # at 30, 60, 90 s
    lines.update(entries, finished=4, force=True)  # the last one, at the end
    text = out.getvalue().splitlines()
    assert text[0] == "[0:00:30] 2/5 finished: submitted 4 · running 1 · done 2 · failed 2"
    assert text[-1].startswith("[0:01:34] 4/5 finished")
    now[0] = 200.0
    assert lines.seconds_to_next() == pytest.approx(24.0)
