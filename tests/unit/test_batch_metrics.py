"""The batch aggregate: means per protocol and stage over the summaries that carry each metric; the outcome's
status and short form that the queue stores beside a job."""

from __future__ import annotations

from typing import Any

import pytest

from common.batch_metrics import (
    MAX_LISTED_REASONS,
    aggregate,
    outcome_columns,
    outcome_status,
    protocol_sections,
    reasons,
    report_columns,
)


def test_aggregate_reads_protocols_by_key_and_older_unit_suffixed_names() -> None:
    summaries: list[dict[str, Any] | None] = [
        {"metrics": {"raw": {"E_t": 2.0, "success": False}, "refined": {"E_t": 0.5, "success": True},
                     "paper": {"raw": {"E_t": 1.5}, "refined": {"E_t": 0.4}}}},
        {"metrics": {"raw": {"E_t_cm": 4.0, "E_r_deg": 20.0}, "refined": {"E_t_cm": 1.5, "success": False}}},
        {"metrics": {"raw": {"E_t": float("nan")}}},  # not finite: not counted in the mean
        None,
        {"kind": "no metrics"},
    ]  # fmt: skip
    out = aggregate(summaries)
    assert set(out) == {"all_frames", "paper"}
    assert out["all_frames"]["raw"]["n"] == 3 and out["all_frames"]["raw"]["E_t"] == pytest.approx(3.0)
    assert out["all_frames"]["raw"]["E_r"] == pytest.approx(20.0) and out["all_frames"]["raw"]["SR"] == 0.0
    assert out["all_frames"]["refined"] == {"n": 2, "SR": 0.5, "E_t": 1.0, "E_r": None, "E_j": None, "E_ft": None,
                                            "penetration_mean_mm": None, "penetration_max_mm": None}  # fmt: skip
    assert out["paper"]["refined"]["n"] == 1 and out["paper"]["refined"]["E_t"] == pytest.approx(0.4)
    assert aggregate([]) == {}


def test_a_protocols_section_and_the_flat_report_columns() -> None:
    summary = {"metrics": {"raw": {"E_t": 1.0}, "refined": {"E_t": 0.5, "success": True}},
               "protocols": {"paper": {"raw": {"E_t": 0.8}, "refined": {"E_t": 0.3}}}}  # fmt: skip
    assert set(protocol_sections(summary)) == {"all_frames", "paper"}
    row = report_columns(summary)
    assert row["all_frames_raw_E_t"] == 1.0 and row["all_frames_refined_SR"] == 1.0
    assert row["paper_refined_E_t"] == 0.3 and row["paper_raw_SR"] is None
    assert len(row) == 2 * 2 * 7


def worker_summary(ref_t: float, paper_t: float, pen: float) -> dict[str, object]:
    """The layout the worker writes: each stage nests the paper's protocol (frames 10 onward)."""
    def stage(e_t: float, p_t: float, ok: bool) -> dict[str, object]:
        return {"E_t": e_t, "E_r": 3.0, "success": ok, "penetration_mean_mm": pen, "penetration_max_mm": 2 * pen,
                "success_first_attempt": ok,
                "paper": {"E_t": p_t, "E_r": 4.0, "success": ok, "penetration_mean_mm": pen + 1, "first_frame": 10}}
    return {"metrics": {"raw": stage(3.0, 3.5, False), "refined": stage(ref_t, paper_t, True),
                        "verification": {"verified": True}}}  # fmt: skip


def test_the_paper_protocol_nested_in_each_stage_and_penetration_are_aggregated() -> None:
    summaries = [worker_summary(0.5, 0.6, 1.0), worker_summary(1.5, 1.8, 3.0)]
    assert set(protocol_sections(summaries[0])) == {"all_frames", "paper"}  # not "verification"
    out = aggregate(summaries)
    assert out["paper"]["refined"]["n"] == 2 and out["paper"]["refined"]["E_t"] == pytest.approx(1.2)
    assert out["paper"]["raw"]["SR"] == 0.0 and out["paper"]["refined"]["SR"] == 1.0
    assert out["all_frames"]["refined"]["penetration_max_mm"] == pytest.approx(4.0)
    assert out["paper"]["refined"]["penetration_mean_mm"] == pytest.approx(3.0)
    row = report_columns(summaries[1])
    assert row["paper_refined_E_t"] == 1.8 and row["all_frames_refined_penetration_mean_mm"] == 3.0


REASON = {"code": "recording_too_fast", "frame": 41, "value": 38.5, "unit": "deg/frame",
          "message": "the recorded object turns 38.5 degrees between frames 41 and 42"}  # fmt: skip


def test_outcome_status_and_the_short_form_kept_beside_a_job() -> None:
    failed = {**worker_summary(4.0, 5.0, 1.0), "outcome": {"executable": False, "protocol": "paper",
                                                            "reasons": [REASON]}}  # fmt: skip
    status, detail = outcome_columns(failed)
    assert status == "not_executable"
    assert detail == {"protocol": "paper", "reasons": [REASON], "reasons_total": 1, "protocol_metrics": "paper",
                      "E_t": 5.0, "E_r": 4.0}  # fmt: skip
    ok = {**worker_summary(0.5, 0.6, 1.0), "outcome": {"executable": True, "protocol": "paper", "reasons": []}}
    assert outcome_columns(ok)[0] == "executable" and outcome_columns(ok)[1]["E_t"] == 0.6
    # A result made before outcomes existed: unknown, its figures on all frames.
    status, detail = outcome_columns(worker_summary(0.5, 0.6, 1.0))
    assert status == "unknown" and detail["protocol"] is None and detail["protocol_metrics"] == "all_frames"
    assert detail["E_t"] == 0.5 and detail["reasons"] == []
    assert outcome_status(None) == "unknown" and outcome_status({"outcome": {"executable": "yes"}}) == "unknown"
    # Also where the worker puts it among the job's metrics.
    assert outcome_status({"metrics": {"outcome": {"executable": True}}}) == "executable"


def test_reasons_are_normalised_and_the_short_form_is_bounded() -> None:
    messy = [REASON, {"code": 7}, "text", {"code": "hand_never_touches", "frame": True, "value": float("nan"),
                                           "unit": 3, "message": None}]  # fmt: skip
    assert reasons({"executable": False, "reasons": messy}) == [
        REASON, {"code": "hand_never_touches", "frame": None, "value": None, "unit": None, "message": ""}]
    many = {"outcome": {"executable": False, "protocol": "paper", "reasons": [REASON] * 20}}
    _, detail = outcome_columns(many)
    assert len(detail["reasons"]) == MAX_LISTED_REASONS and detail["reasons_total"] == 20
    assert detail["protocol_metrics"] is None and detail["E_t"] is None
