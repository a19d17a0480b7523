"""What made honest results fail ``verify`` on other CPU kernels (issue #54, bench/results/verify_portable.md): the
table fit's near tie, decided by last bits, and the articulation error compared to the last bit. A result records
its table choice and ``verify`` accepts it when the fit re-derives it as a near-best candidate; E_a / max_E_a get
the tolerance E_r has."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.job_options import JobOptions
from common.result_format import STEPWISE_KEYS, read_arrays, read_summary, write_result_npz
from tests.support.verify_failures import fails_naming
from worker.refine.result import prepare_from_result
from worker.refine.run import RefineOutcome, refine_sequence
from worker.simulation import table_fit
from worker.simulation.table_fit import SCORE_MARGIN, TableChoice, TableFit, score_margin
from worker.verification import CROSS_HOST, STEPWISE, check_result

ROOT = Path(__file__).resolve().parents[2]
#: NumPy's baseline kernels and OpenBLAS's Nehalem ones: what an SSE-only host runs.
SSE_KERNELS = {"NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR AVX512_SKX",
               "OPENBLAS_CORETYPE": "Nehalem"}

Result = tuple[dict[str, np.ndarray], dict[str, Any]]


@pytest.fixture(scope="module")
def honest() -> Result:
    """The built-in grasp-and-lift refined cheaply: its fit has four candidates, the best (a table tilted 0.14 deg)
    0.34 ahead of a level one and more than 1 ahead of the other two."""
    from worker.example import short_example_sequence

    outcome = refine_sequence(short_example_sequence(), JobOptions(popsize=4, max_generations=1, restarts=0))
    blob = outcome.to_npz_bytes(wall_clock=False)
    return read_arrays(blob), read_summary(blob)


@pytest.fixture(scope="module")
def fit(honest: Result) -> TableFit:
    fit = prepare_from_result(write_result_npz(*honest, wall_clock=False))[0].scene.table_fit
    assert fit is not None
    return fit


def _blob(arrays: dict[str, np.ndarray], summary: dict[str, Any]) -> bytes:
    return write_result_npz(arrays, summary, wall_clock=False)


def _ranked(fit: TableFit) -> tuple[int, int, int]:
    """The best candidate, the nearest one within the margin of it, and one beyond the margin."""
    order = [int(i) for i in np.argsort(fit.scores)]
    best = order[0]
    near = [i for i in order[1:] if fit.scores[i] <= fit.scores[best] + score_margin(fit.scores[i])]
    far = [i for i in order[1:] if fit.scores[i] > fit.scores[best] + score_margin(fit.scores[i])]
    assert near and far, fit.scores
    assert fit.candidates[near[0]][1].normal.tolist() != fit.candidates[best][1].normal.tolist()
    return best, near[0], far[0]


def test_a_result_records_the_fits_choice(honest: Result, fit: TableFit) -> None:
    _, summary = honest
    table = summary["table"]
    assert table["candidate"] == int(np.argmin(fit.scores)) == fit.candidate
    assert table["drift"] == fit.drift and table["pose"] == fit.pose.tolist()
    choice = TableChoice.from_summary(table)
    assert choice is not None and choice.plane.normal.tolist() == table["normal"]


def test_a_near_tie_other_kernels_decide_verifies_on_the_stored_choice(
    honest: Result, fit: TableFit, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Here the re-derived scores are perturbed so that another candidate, within the margin, wins (as the SSE
    kernels do on 20200813-subject-02__20200813_153152): the stored choice still verifies, with a note; the same
    result without its choice (older, checked the old way) fails naming the table it re-fits."""
    best, near, _ = _ranked(fit)
    scores = fit.scores
    real = table_fit._drift_scores

    def swapped(*args: Any, **kwargs: Any) -> list[float]:
        out = list(real(*args, **kwargs))
        assert out == list(scores)  # the same fit as the result's
        out[best], out[near] = scores[near], scores[best]
        return out

    monkeypatch.setattr(table_fit, "_drift_scores", swapped)
    arrays, summary = honest
    report = check_result(_blob(arrays, summary))
    assert report.failures == [], report.failures
    assert any("near tie" in n for n in report.config_notes), report.config_notes
    old = {k: v for k, v in summary["table"].items() if k not in ("candidate", "pose", "drift")}
    fails_naming(_blob(arrays, {**summary, "table": old}), "table.normal")


def _derived_on(honest: Result, choice: TableChoice) -> bytes:
    """The honest result's keyframes re-derived whole on another table: every array and figure consistent with it."""
    from worker.refine.derive import add_attempt_metrics, attempt_figures, derive_result
    from worker.refine.outcome import classify_outcome
    from worker.simulation.config import SimConfig
    from worker.simulation.metrics import scalar_metrics

    arrays, summary = honest
    derived = derive_result(arrays["sequence_npz"].tobytes(), JobOptions.model_validate(summary["options"]),
                            SimConfig(), summary["config"]["rotation_pivot"], {"right": arrays["right_keyframes"]},
                            table=choice)
    metrics = {k: scalar_metrics(v) for k, v in derived.metrics.items()}
    attempts = [{**attempt_figures(derived.metrics["refined"]), "seed": 0, "evaluations": 1}]
    add_attempt_metrics(metrics["refined"], attempts)
    contact = derived.final.contact_frames
    outcome = classify_outcome(derived.prep, derived.metrics["refined"], derived.final.object_pose,
                               hand_contact=None if contact is None else contact.hand)
    forged = {**summary, "metrics": metrics, "attempts": attempts, "table": derived.prep.scene.table_summary(),
              "object_hold": derived.prep.scene.hold_summary(),
              "num_contacts": len(derived.final.contacts["contact_frame"]), "outcome": outcome.model_dump(mode="json")}
    return RefineOutcome(dict(derived.arrays), forged).to_npz_bytes(wall_clock=False)


def test_a_result_on_a_table_the_fit_would_not_choose_fails(honest: Result, fit: TableFit) -> None:
    """Everything re-derived on a candidate scoring beyond the margin fails naming the table's candidate; one on the
    near-best candidate verifies (the margin is what it says); a plane moved off every candidate fails naming it."""
    best, near, far = _ranked(fit)
    for i, verifies in ((near, True), (far, False)):
        pose, plane = fit.candidates[i]
        blob = _derived_on(honest, TableChoice(i, pose, plane))
        if verifies:
            assert check_result(blob).failures == []
        else:
            fails_naming(blob, "table.candidate", f"more than {score_margin(fit.scores[i]):g} worse than the best")
    arrays, summary = honest
    tilted = np.asarray(summary["table"]["normal"]) + np.array([1e-4, 0.0, 0.0])
    moved = {**summary["table"], "normal": (tilted / np.linalg.norm(tilted)).tolist()}
    fails_naming(_blob(arrays, {**summary, "table": moved}), "table.normal: stored", f"candidate {best} re-derived")
    unreadable = {**summary["table"], "pose": [0.0, 1.0]}
    fails_naming(_blob(arrays, {**summary, "table": unreadable}), "table: the stored choice is not readable")


def test_the_articulation_error_has_the_rotations_tolerance() -> None:
    for tol in (CROSS_HOST, STEPWISE):
        for key in ("E_a", "max_E_a"):
            assert tol.summary_limit(key, 2.0) == tol.summary_limit("E_r", 2.0)
            slide = tol.for_joints(("prismatic",)).summary_limit(key, 2.0)
            assert slide == tol.summary_limit("E_t", 2.0)
    assert CROSS_HOST.for_joints(("revolute", "prismatic")).summary_limit("E_a", 1.0) == 5.1


def test_the_hinged_box_verifies_the_old_way_with_sse_kernels_forced(tmp_path: Path) -> None:
    """Whole re-simulated with other kernels (its states left out), the hinged box's E_a moved by 7e-7 deg and
    failed against 1e-9; now it has E_r's tolerance there. (With restarts and the polish: the cheaper result of
    ``tests.support.results`` happens to re-simulate bit for bit there.)"""
    from worker.example.hinged_box import short_hinged_box_sequence

    blob = refine_sequence(short_hinged_box_sequence(), JobOptions(popsize=4, max_generations=1)).to_npz_bytes()
    arrays = {k: v for k, v in read_arrays(blob).items() if k not in STEPWISE_KEYS}
    path = tmp_path / "hinged_box_old_way.npz"
    path.write_bytes(write_result_npz(arrays, read_summary(blob)))
    run = subprocess.run([sys.executable, "-m", "common.cli", "verify", str(path)], cwd=ROOT, capture_output=True,
                         text=True, timeout=600, env={**os.environ, **SSE_KERNELS, "PYTHONPATH": str(ROOT)})
    assert run.returncode == 0, run.stdout + run.stderr
    assert "verify: OK" in run.stdout


def test_a_large_score_may_move_by_a_share_of_itself() -> None:
    """Where every candidate leaves the object far from rest, a score moves by a share of itself between kernels
    (measured 15.67 -> 14.07): the margin grows with the score, and stays the absolute one for small scores."""
    assert score_margin(0.3) == SCORE_MARGIN and score_margin(15.67) >= 15.67 - 14.07
    assert score_margin(100.0) < 100.0 - 1.0  # a candidate that drifts far stays far from a good one
