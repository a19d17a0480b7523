"""The rescue of a failed refinement on finer convex parts (worker/refine/run.py ``RESCUE``): when every attempt
fails on an object split into convex parts, the plan runs again on finer parts and the better is kept; the result
lists every attempt with the parts it ran on, and ``verify`` replays each on its own parts."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import trimesh

from common.job_options import JobOptions
from common.result_format import read_arrays, read_summary, write_result_npz
from common.sequence import ObjectSpec, Sequence
from tests.support.synthetic_push import push_sequence
from worker.refine.prepare import prepare
from worker.refine.run import RefineOutcome, attempt_rank, refine_sequence, rescue_due
from worker.simulation.config import SimConfig
from worker.verification import check_result

#: Two attempts of a tiny budget, no polish: the rescue's cost in a test is two more.
QUICK = JobOptions(seed=0, popsize=4, max_generations=2, restarts=1, polish=False)


def _ring_push(lift_m: float) -> Sequence:
    """The synthetic push with a flat ring (non-convex: CoACD splits it) in place of the box, recorded rising
    ``lift_m`` over the second while the hand stays on the table (0: at rest)."""
    ring = trimesh.creation.annulus(r_min=0.02, r_max=0.035, height=0.02, sections=16)
    frames = 30
    pose = np.tile([0.0, 0.0, 0.01, 1.0, 0.0, 0.0, 0.0], (frames, 1))
    pose[:, 2] += np.linspace(0.0, lift_m, frames)
    seq = push_sequence(frames, object_pose=pose)
    ring_spec = ObjectSpec(name="ring", mass_kg=0.1, mesh_vertices=np.asarray(ring.vertices),
                           mesh_faces=np.asarray(ring.faces, dtype=np.int64))
    return replace(seq, object=ring_spec, name="synthetic-ring-lift").validate()


@pytest.fixture(scope="module")
def rescued() -> RefineOutcome:
    # No hand motion lifts a ring 20 cm off the table while the hand stays on it: every attempt fails.
    return refine_sequence(_ring_push(0.2), QUICK, threads=2)


def test_a_failed_refinement_on_a_decomposed_object_runs_again_on_finer_parts(rescued: RefineOutcome) -> None:
    summary = rescued.summary
    attempts = summary["attempts"]
    assert [a["convex_detail"] for a in attempts] == ["coarse", "coarse", "fine", "fine"]
    assert not any(a["success"] for a in attempts)
    # The kept result is the best-ranked attempt, on the parts it ran on.
    best = max(attempts, key=attempt_rank)
    refined = summary["metrics"]["refined"]
    assert summary["config"]["sim"]["convex_detail"] == best["convex_detail"]
    assert (refined["E_t"], refined["E_r"]) == (best["E_t"], best["E_r"])
    # The paper runs one attempt: the first-attempt figure is the product's first, on the coarse parts.
    assert refined["success_first_attempt"] is attempts[0]["success"]
    # The outcome says why it fails (the ring rises where the hand does not lift it) and whether it was rescued.
    outcome = summary["outcome"]
    codes = [r["code"] for r in outcome["reasons"]]
    assert outcome["executable"] is False and codes[0] in ("not_lifted", "slipped", "off_track"), codes
    assert ("rescued_on_finer_parts" in codes) == (summary["config"]["sim"]["convex_detail"] == "fine")


def test_a_rescued_result_verifies_bit_for_bit(rescued: RefineOutcome) -> None:
    report = check_result(rescued.to_npz_bytes())
    assert report.failures == [] and report.exact
    assert report.config_changes == []
    if rescued.summary["config"]["sim"]["convex_detail"] == "fine":
        assert any("the rescue after 2 failed attempt(s)" in n for n in report.config_notes), report.config_notes


def test_an_attempt_claimed_on_other_convex_parts_fails(rescued: RefineOutcome) -> None:
    blob = rescued.to_npz_bytes()
    arrays, summary = read_arrays(blob), read_summary(blob)
    summary["attempts"][2]["convex_detail"] = "coarse"  # a rescue attempt claimed on the product's parts
    report = check_result(write_result_npz(arrays, summary))
    assert any(f.startswith("attempts[2].") for f in report.failures), report.failures


def test_finer_parts_without_failed_coarse_attempts_are_a_non_default_config() -> None:
    seq = _ring_push(0.2)
    outcome = refine_sequence(seq, QUICK.model_copy(update={"restarts": 0}), config=SimConfig(convex_detail="fine"))
    assert [a["convex_detail"] for a in outcome.summary["attempts"]] == ["fine"]
    blob = outcome.to_npz_bytes()
    report = check_result(blob)
    assert any("sim.convex_detail" in f and "no attempt on them" in f for f in report.failures), report.failures
    allowed = check_result(blob, allow_config=True)
    assert allowed.failures == [] and allowed.config_changes == [("sim.convex_detail", "coarse", "fine")]


@pytest.mark.parametrize(
    ("case", "due"),
    [("failed", True), ("succeeded", False), ("one attempt asked", False), ("already fine", False),
     ("primitive", False), ("convex mesh", False)],
)
def test_the_rescue_runs_only_after_a_failure_on_a_decomposed_object(case: str, due: bool) -> None:
    seq, options, config = _ring_push(0.0), QUICK, SimConfig()
    if case == "primitive":
        seq = push_sequence(30)
    elif case == "convex mesh":
        box = trimesh.creation.box(extents=[0.06, 0.06, 0.06])
        seq = replace(seq, object=ObjectSpec(name="box", mass_kg=0.2, mesh_vertices=np.asarray(box.vertices),
                                             mesh_faces=np.asarray(box.faces, dtype=np.int64)))
    elif case == "one attempt asked":
        options = options.model_copy(update={"restarts": 0})
    elif case == "already fine":
        config = SimConfig(convex_detail="fine")
    prep = prepare(seq, options, config)
    best: dict[str, Any] = {"success": case == "succeeded"}
    assert rescue_due(best, prep, options) is due


def test_an_unknown_convex_detail_is_refused() -> None:
    with pytest.raises(ValueError, match="convex_detail must be one of coarse, fine"):
        SimConfig(convex_detail="finest")
