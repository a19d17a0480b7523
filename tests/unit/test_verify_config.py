"""``verify``'s config check (issue #15 item 1) across a change of the product's physics defaults (issue #19): a
result made with an earlier complete set of defaults is checked against that set; a mix is non-default."""

from __future__ import annotations

from typing import Any

from worker.refine.prepare import MIRROR_LEFT_HAND, ROTATION_PIVOT
from worker.refine.verify import EARLIER_DEFAULTS, _config
from worker.refine.verify_report import VerifyReport
from worker.simulation.config import SimConfig


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


def test_a_mix_of_old_and_new_physics_is_a_non_default_config() -> None:
    report = VerifyReport()
    _config(_stored(noslip_iterations=10), report, allow_config=False)  # old noslip, new impratio and solimp
    assert [c[0] for c in report.config_changes] == ["sim.noslip_iterations"]
    assert report.failures and "--allow-config" in report.failures[0]


def test_a_result_that_predates_the_jacobian_setting_reads_it_as_auto() -> None:
    """Results made before issue #19's sparse Jacobian ran MuJoCo's automatic choice; they verify with a note."""
    stored_config = _stored()
    del stored_config["sim"]["jacobian"]
    report = VerifyReport()
    stored, _, _ = _config(stored_config, report, allow_config=False)
    assert report.failures == [] and stored["jacobian"] == "auto"
    assert any("jacobian not recorded" in note for note in report.config_notes)
