"""The outcome contract shared by the worker, the service and the client (``common.outcome``)."""

from __future__ import annotations

import re

import pytest
from pydantic import ValidationError

from common.outcome import (
    FAILURE_CODES,
    REASON_DESCRIPTIONS,
    Outcome,
    OutcomeReason,
    ReasonCode,
    outcome_of,
)


def test_codes_are_snake_case_and_described() -> None:
    required = {"recording_too_fast", "unsupported_start", "hand_sparse", "no_contact", "fingers_through_object",
                "slipped"}
    assert required <= {c.value for c in ReasonCode}
    for code in ReasonCode:
        assert re.fullmatch(r"[a-z]+(_[a-z]+)*", code.value)
        assert REASON_DESCRIPTIONS[code]
    assert ReasonCode.RESCUED_ON_FINER_PARTS not in FAILURE_CODES


def test_round_trip_and_primary() -> None:
    doc = {"executable": False, "protocol": "paper", "reasons": [
        {"code": "recording_too_fast", "frame": 41, "value": 87.5, "unit": "deg/frame",
         "message": "The recorded object turns 87.5 deg between frames 40 and 41."},
        {"code": "slipped", "frame": 41, "value": 80.0, "unit": "deg", "message": "x"}]}
    out = Outcome.model_validate(doc)
    assert out.model_dump(mode="json") == doc
    primary = out.primary()
    assert primary is not None and primary.code == ReasonCode.RECORDING_TOO_FAST
    assert not out.rescued


def test_unknown_code_unit_and_extra_fields_are_refused() -> None:
    with pytest.raises(ValidationError):
        OutcomeReason.model_validate({"code": "gremlins", "message": "x"})
    with pytest.raises(ValidationError):
        OutcomeReason.model_validate({"code": "slipped", "unit": "furlong", "message": "x"})
    with pytest.raises(ValidationError):
        Outcome.model_validate({"executable": True, "protocol": "all", "reasons": []})
    with pytest.raises(ValidationError):
        Outcome.model_validate({"executable": True, "reasons": [], "extra": 1})


def test_outcome_of_old_summaries_and_job_metrics() -> None:
    stored = {"executable": True, "protocol": "paper", "reasons": [
        {"code": "rescued_on_finer_parts", "frame": None, "value": None, "unit": None, "message": "kept"}]}
    assert outcome_of({"outcome": stored}) == Outcome.model_validate(stored)
    assert outcome_of({"outcome": stored}).rescued  # type: ignore[union-attr]
    old = {"metrics": {"refined": {"paper": {"success": False}}}}
    assert outcome_of(old) == Outcome(executable=False)
    job_metrics = {"refined": {"paper": {"success": True}}, "raw": {}}
    assert outcome_of(job_metrics) == Outcome(executable=True)
    assert outcome_of({"kind": "replay", "metrics": {"raw": {}}}) is None
