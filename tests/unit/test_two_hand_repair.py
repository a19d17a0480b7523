"""The local repair of a failed two-handed or articulated attempt (worker.refine.repair): only the windows around
the first frame past the limit are searched again, a round is kept only when the whole-sequence score ranks
higher, and the next round starts at the failure left."""

from __future__ import annotations

from typing import Any

import numpy as np

from common.job_options import JobOptions
from worker.refine import repair as R
from worker.refine.run import local_polish, repair_due
from worker.refine.windowed import CmaSettings, WindowLog

INTERVAL = 5
N_KEYFRAMES = 24


class SlipProblem:
    """A window problem without physics for two hands: keyframe j of each hand should be 0; window j is scored on
    keyframes j and j + 1 (a lookahead). It records the windows it evaluates."""

    sides: tuple[str, ...] = ("right", "left")
    n_keyframes = N_KEYFRAMES
    first_window = 1

    def __init__(self) -> None:
        self.evaluated: set[int] = set()
        self.commits = 0

    def dim(self, side: str) -> int:
        return 2

    def start_state(self) -> Any:
        return 0

    def _loss(self, here: np.ndarray, after: np.ndarray) -> np.ndarray:
        return np.asarray(np.sum(here**2, axis=-1) + np.sum(after**2, axis=-1))

    def probe(self, j: int, state: Any, keyframes: dict[str, np.ndarray]) -> tuple[dict[str, float], bool]:
        after = min(j + 1, N_KEYFRAMES - 1)
        return {s: float(self._loss(k[j], k[after])) for s, k in keyframes.items()}, True

    def evaluate(self, j: int, state: Any, keyframes: dict[str, np.ndarray], candidates: dict[str, np.ndarray],
                 hold: bool = True) -> dict[str, np.ndarray]:
        assert state == j - 1, "a band's window starts from the state committed up to it"
        self.evaluated.add(j)
        after = min(j + 1, N_KEYFRAMES - 1)
        return {s: self._loss(c, np.broadcast_to(keyframes[s][after], c.shape)) for s, c in candidates.items()}

    def commit(self, j: int, state: Any, keyframes: dict[str, np.ndarray]) -> Any:
        self.commits += 1
        return state + 1


def score(keyframes: dict[str, np.ndarray]) -> dict[str, Any]:
    """Metrics of keyframes as a replay's: frame f is off by the largest keyframe near it (x 10 cm)."""
    worst = np.max([np.abs(k).max(axis=1) for k in keyframes.values()], axis=0)  # (N,)
    frames = np.arange((N_KEYFRAMES - 1) * INTERVAL + 1)
    e_t = 10.0 * worst[np.minimum(frames // INTERVAL, N_KEYFRAMES - 1)]
    e_r = np.zeros_like(e_t)
    ok = bool(np.all(e_t[10:] <= 3.0))
    return {"success": ok, "paper": {"success": ok}, "per_frame": {"e_t_cm": e_t, "e_r_deg": e_r},
            "E_t": float(e_t.mean()), "E_r": 0.0}


SETTINGS = CmaSettings(popsize=8, max_generations=12, skip_loss=0.0, seed=1)


def slipped() -> dict[str, np.ndarray]:
    kf = {s: np.zeros((N_KEYFRAMES, 2)) for s in SlipProblem.sides}
    kf["left"][14] = [1.0, -0.8]  # the left hand loses the object between keyframes 13 and 15
    kf["right"][15] = [0.6, 0.6]
    return kf


def test_the_repair_searches_only_the_windows_around_the_first_failure_and_fixes_it() -> None:
    problem, kf = SlipProblem(), slipped()
    before = score(kf)
    assert not before["success"] and R.repair_rank(before) < R.repair_rank(score({s: 0 * k for s, k in kf.items()}))
    logs = [WindowLog(j, False, True, 1.0, 1.0, 10) for j in range(1, N_KEYFRAMES)]
    fixed = R.repair(problem, SETTINGS, kf, before, logs, INTERVAL, score, attempt_evaluations=10_000)
    assert fixed.metrics["success"], fixed.metrics["per_frame"]["e_t_cm"]
    assert fixed.kept >= 1 and fixed.rounds == fixed.kept
    first_fail = 14 * INTERVAL
    start, stop = R.band_of(first_fail, INTERVAL, N_KEYFRAMES, 1, R.REPAIR_BACKTRACK)
    assert (start, stop) == (12, 17)
    assert problem.evaluated <= set(range(start, N_KEYFRAMES)) and start in problem.evaluated
    assert not problem.evaluated & set(range(1, start))  # nothing before the band is searched again
    np.testing.assert_array_equal(slipped()["left"], kf["left"])  # the attempt's keyframes are not written to
    assert np.abs(fixed.keyframes["left"][14]).max() < 0.3
    replaced = {w.index for w in fixed.logs if w.evaluations != 10}
    assert replaced and replaced <= set(range(start, N_KEYFRAMES))


def test_a_failure_the_band_pushes_further_on_is_chased_by_the_next_round() -> None:
    """Fixing keyframe 14 loses the object at keyframe 20 while that keyframe is still the attempt's (chosen for
    the state the attempt had there): the first round ranks lower, the next one chases the new failure."""
    problem, kf = SlipProblem(), slipped()
    kf["right"][20] = [0.01, 0.0]

    def rippling(k: dict[str, np.ndarray]) -> dict[str, Any]:
        m = score(k)
        if np.abs(k["left"][14]).max() < 0.3 and k["right"][20].tolist() == [0.01, 0.0]:
            e_t = m["per_frame"]["e_t_cm"].copy()
            e_t[20 * INTERVAL:] = 5.0  # dropped for good
            m = {**m, "success": False, "paper": {"success": False}, "E_t": float(e_t.mean()),
                 "per_frame": {**m["per_frame"], "e_t_cm": e_t}}
        return m

    fixed = R.repair(problem, SETTINGS, kf, rippling(kf), [], INTERVAL, rippling, attempt_evaluations=10_000)
    assert fixed.metrics["success"] and fixed.rounds >= 2 and fixed.kept >= 1
    assert {19, 20} <= problem.evaluated


def test_a_round_that_ranks_lower_is_not_kept_and_the_repair_gives_up_after_a_wider_one() -> None:
    problem, kf = SlipProblem(), slipped()
    before = score(kf)
    calls = []

    def worse(k: dict[str, np.ndarray]) -> dict[str, Any]:
        calls.append(k)
        m = score(k)
        return {**m, "success": False, "paper": {"success": False}, "E_t": before["E_t"] + 1.0,
                "per_frame": {**m["per_frame"], "e_t_cm": before["per_frame"]["e_t_cm"] + 1.0}}

    fixed = R.repair(problem, SETTINGS, kf, before, [], INTERVAL, worse, attempt_evaluations=10_000)
    assert (fixed.rounds, fixed.kept) == (2, 0) and len(calls) == 2  # the round, then once from further back
    assert fixed.metrics is before and fixed.keyframes["left"][14].tolist() == [1.0, -0.8]


def test_the_repair_stops_at_its_evaluation_budget() -> None:
    fixed = R.repair(SlipProblem(), SETTINGS, slipped(), score(slipped()), [], INTERVAL, score,
                     attempt_evaluations=1)
    assert fixed.rounds == 1  # one round always runs; its cost ends the repair


def test_only_two_handed_or_articulated_sequences_get_the_local_repair() -> None:
    class Prep:
        def __init__(self, hands: int, joints: int) -> None:
            self.references = [object()] * hands
            self.layout = type("L", (), {"n_joints": joints})()

    failed, options = {"success": False}, JobOptions(local_repair=True)
    assert not repair_due(failed, Prep(2, 1), JobOptions())  # type: ignore[arg-type]  # off by default
    assert not local_polish(Prep(1, 0), options) and not repair_due(failed, Prep(1, 0), options)  # type: ignore[arg-type]
    assert repair_due(failed, Prep(2, 0), options) and repair_due(failed, Prep(1, 1), options)  # type: ignore[arg-type]
    assert not repair_due({"success": True}, Prep(2, 1), options)  # type: ignore[arg-type]
    assert not repair_due(failed, Prep(2, 1), JobOptions(polish=False, local_repair=True))  # type: ignore[arg-type]
