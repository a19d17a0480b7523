"""Bulk submit's closing summary: counts per state and mean raw vs refined metrics."""

from __future__ import annotations

import io

from rich.console import Console

from service.submit.manifest import Entry
from service.submit.report import counts, metric_means, print_summary


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
