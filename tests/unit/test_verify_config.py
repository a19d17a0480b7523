"""``verify``'s config check (issue #15 item 1) across a change of the product's physics defaults (issue #19): a
result made with an earlier complete set of defaults is checked against that set; a mix is non-default."""

from __future__ import annotations

from typing import Any

import pytest

from worker.refine.prepare import MIRROR_LEFT_HAND, ROTATION_PIVOT
from worker.refine.result import sim_config_from_summary
from worker.simulation.config import SimConfig
from worker.verification.check import EARLIER_DEFAULTS, _config
from worker.verification.report import VerifyReport


def _stored(**sim: Any) -> dict[str, Any]:
    return {"sim": {**SimConfig().to_dict(), **sim}, "rotation_pivot": ROTATION_PIVOT,
            "left_hand_controls": "mirrored" if MIRROR_LEFT_HAND else "as right"}


def test_todays_defaults_pass_without_notes() -> None:
    report = VerifyReport()
    _config(_stored(), report, allow_config=False)
    assert report.failures == [] and report.config_changes == [] and report.config_notes == []


def test_a_result_made_with_the_defaults_before_issue_19_verifies_with_a_note() -> None:
    report = VerifyReport()
    stored, _, _ = _config(_stored(**EARLIER_DEFAULTS["before issue #19"]), report, allow_config=False)
    assert report.failures == [] and report.config_changes == []
    assert any("before issue #19" in note for note in report.config_notes)
    assert stored["noslip_iterations"] == 10 and stored["impratio"] == 1.0  # the replay uses what was stored


def test_a_result_that_predates_impratio_reads_it_as_one() -> None:
    """Made before impratio was recorded: its noslip 10 and solimp with the unrecorded impratio form the old set."""
    sim = {k: v for k, v in EARLIER_DEFAULTS["before issue #19"].items() if k != "impratio"}
    stored_config = _stored(**sim)
    del stored_config["sim"]["impratio"]
    report = VerifyReport()
    stored, _, _ = _config(stored_config, report, allow_config=False)
    assert report.failures == [] and stored["impratio"] == 1.0


def test_a_result_made_before_primitive_surface_points_verifies_with_a_note() -> None:
    """Recorded as 0 while that was the default (a primitive known by its vertices): replayed as made, a note."""
    report = VerifyReport()
    stored, _, _ = _config(_stored(primitive_surface_spacing_m=0.0), report, allow_config=False)
    assert report.failures == [] and report.config_changes == []
    assert any("before primitive surface points" in note for note in report.config_notes)
    assert stored["primitive_surface_spacing_m"] == 0.0


def test_another_primitive_spacing_is_a_non_default_config() -> None:
    report = VerifyReport()
    _config(_stored(primitive_surface_spacing_m=0.01), report, allow_config=False)
    assert [c[0] for c in report.config_changes] == ["sim.primitive_surface_spacing_m"]
    assert report.failures and "--allow-config" in report.failures[0]


def test_a_mix_of_old_and_new_physics_is_a_non_default_config() -> None:
    report = VerifyReport()
    _config(_stored(noslip_iterations=10), report, allow_config=False)  # old noslip, new impratio and solimp
    assert [c[0] for c in report.config_changes] == ["sim.noslip_iterations"]
    assert report.failures and "--allow-config" in report.failures[0]


@pytest.mark.parametrize(("name", "then"), [("jacobian", "auto"), ("table_fit_s", 0.5), ("table_shelf", False),
                                          ("primitive_surface_spacing_m", 0.0)])
def test_a_result_that_predates_a_setting_reads_it_as_it_was_then(name: str, then: Any) -> None:
    """Results made before issue #19's sparse Jacobian ran MuJoCo's automatic choice, before the support fix of
    issue #15 a 0.5 s table fit without the shelf; they verify with a note and replay as they were made."""
    stored_config = _stored()
    del stored_config["sim"][name]
    report = VerifyReport()
    stored, _, _ = _config(stored_config, report, allow_config=False)
    assert report.failures == [] and stored[name] == then
    assert any(f"{name} not recorded" in note for note in report.config_notes)
    assert getattr(sim_config_from_summary({k: v for k, v in stored_config["sim"].items()}), name) == then
