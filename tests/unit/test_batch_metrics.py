"""The batch aggregate: means per protocol and stage over the summaries that carry each metric."""

from __future__ import annotations

import pytest

from common.batch_metrics import aggregate, protocol_sections, report_columns


def test_aggregate_reads_protocols_by_key_and_older_unit_suffixed_names() -> None:
    summaries = [
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
    assert out["all_frames"]["refined"] == {"n": 2, "SR": 0.5, "E_t": 1.0, "E_r": None, "E_j": None, "E_ft": None}
    assert out["paper"]["refined"]["n"] == 1 and out["paper"]["refined"]["E_t"] == pytest.approx(0.4)
    assert aggregate([]) == {}


def test_a_protocols_section_and_the_flat_report_columns() -> None:
    summary = {"metrics": {"raw": {"E_t": 1.0}, "refined": {"E_t": 0.5, "success": True}},
               "protocols": {"paper": {"raw": {"E_t": 0.8}, "refined": {"E_t": 0.3}}}}  # fmt: skip
    assert set(protocol_sections(summary)) == {"all_frames", "paper"}
    row = report_columns(summary)
    assert row["all_frames_raw_E_t"] == 1.0 and row["all_frames_refined_SR"] == 1.0
    assert row["paper_refined_E_t"] == 0.3 and row["paper_raw_SR"] is None
    assert len(row) == 2 * 2 * 5
