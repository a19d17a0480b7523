"""Local repair of a failed attempt on a two-handed or articulated sequence (issue #52).

On a 600-frame ARCTIC sequence a whole-sequence restart or polish sweep costs a full run (7-15 min on two cores),
while a near miss leaves the limit on a few short stretches only. The repair re-optimises the windows around the
first frame past the paper's limit (``outcome.first_past_limit``): from ``REPAIR_BACKTRACK`` keyframes before it,
where the grasp that lost the object was committed, to ``REPAIR_AHEAD`` after it, as a polish pass (each window
starts from the attempt's keyframe and sees the later keyframes as they are, ``windowed.Band``) with a wider search
than the first pass (``repair_settings``). The whole-sequence replay decides: a round is kept when it ranks higher
(``repair_rank``: success, then fewer frames past the limit, then the object error), and the next round starts at
the first failure left. A band that holds the object past the failing frame often loses it a little later, where
the attempt's later keyframes, chosen for the state the attempt had there, meet another one: the next round then
chases that failure from the band's keyframes (kept only once the whole replay ranks higher than the best so far).
A round that neither ranks higher nor moves the failure on is tried once more from the best so far, twice as far
back with a wider step, before the repair gives up; it also stops after ``REPAIR_ROUNDS`` rounds or once it spent
``REPAIR_BUDGET`` x the attempt's candidate evaluations. ``worker.refine.run`` runs it after an attempt that
failed (``repair_due``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from common.geometry import FloatArray
from worker.refine.outcome import first_past_limit, past_limit
from worker.refine.windowed import Band, CmaSettings, RefineProgress, WindowLog, WindowProblem, optimise_windows

#: Keyframes before the first failing frame's where the band starts: the slip shows a few frames after the
#: grasp that lost the object was committed (a window commits keyframe j - 1, two intervals before its last frame).
REPAIR_BACKTRACK = 2
#: Keyframes after the failing frame's that the band still re-optimises (its lookahead reaches further).
REPAIR_AHEAD = 2
#: Rounds at most (each one band and one whole-sequence replay); the budget usually ends it first.
REPAIR_ROUNDS = 12
#: The repair stops once its candidate evaluations reach this share of the attempt's.
REPAIR_BUDGET = 0.5
#: The band's search: the first pass's step (not the polish's half step, the band must leave where the attempt
#: lost the grasp) with this factor on the population; a widened round also takes 1.5 x the step.
REPAIR_POPULATION_FACTOR = 2
#: The first random stream of the repair's rounds (``windowed`` uses 0-3 for the first pass and the polish).
FIRST_STREAM = 4


@dataclass
class Repaired:
    """What a repair made: the keyframes and replay metrics it kept (the attempt's when no round was kept), the
    window logs with the kept bands' windows replaced, the rounds run and kept, the candidate evaluations spent."""

    keyframes: dict[str, FloatArray]
    metrics: dict[str, Any]
    logs: list[WindowLog]
    rounds: int
    kept: int
    evaluations: int


def repair_rank(m: dict[str, Any]) -> tuple[bool, bool, int, float]:
    """How repair rounds are ranked (higher is better): success on both protocols, then the frames past the paper's
    limit (fewer is better), then the object error (``run.object_error``'s units)."""
    from worker.refine.losses import ROT_SCALE

    frames = int(past_limit(m["per_frame"]).sum())
    return (bool(m["success"]), bool(m["paper"]["success"]), -frames,
            -float(m["E_t"] + m["E_r"] / np.degrees(ROT_SCALE)))


def repair_settings(settings: CmaSettings, widened: bool) -> CmaSettings:
    """The CMA-ES settings of a band's windows (see ``REPAIR_POPULATION_FACTOR``)."""
    return replace(settings, popsize=settings.popsize * REPAIR_POPULATION_FACTOR,
                   sigma0=settings.sigma0 * (1.5 if widened else 1.0))


def band_of(fail: int, interval: int, n_keyframes: int, first_window: int, backtrack: int) -> tuple[int, int]:
    """The windows (start, stop) re-optimised for a failure at frame ``fail``."""
    k = fail // interval  # the keyframe at or before the failing frame
    return max(first_window, k - backtrack), min(n_keyframes, k + REPAIR_AHEAD + 1)


def state_at(problem: WindowProblem, keyframes: dict[str, FloatArray], j: int) -> Any:
    """The state at window ``j``'s first frame, simulated from the start with ``keyframes`` (as the pass that
    chose them committed it)."""
    state = problem.start_state()
    for i in range(problem.first_window, j):
        state = problem.commit(i, state, keyframes)
    return state


def repair(
    problem: WindowProblem,
    settings: CmaSettings,
    keyframes: dict[str, FloatArray],
    metrics: dict[str, Any],
    logs: list[WindowLog],
    interval: int,
    score: Callable[[dict[str, FloatArray]], dict[str, Any]],
    attempt_evaluations: int,
    progress: Callable[[RefineProgress], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> Repaired:
    """Repair an attempt (its ``keyframes`` in ``problem``'s sides, its replay ``metrics`` with ``per_frame``,
    its window ``logs``, made with ``settings``); ``score`` replays keyframes from the start and returns their
    metrics. See the module docstring."""
    best = Repaired({s: k.copy() for s, k in keyframes.items()}, metrics, list(logs), 0, 0, 0)
    work_kf, work_m, work_logs = best.keyframes, best.metrics, best.logs
    widened = False
    budget = REPAIR_BUDGET * attempt_evaluations
    while best.rounds < REPAIR_ROUNDS and best.evaluations < budget and not best.metrics["success"]:
        fail = first_past_limit(work_m["per_frame"])
        if fail is None:
            break
        backtrack = REPAIR_BACKTRACK * (2 if widened else 1)
        start, stop = band_of(fail, interval, problem.n_keyframes, problem.first_window, backtrack)
        band = Band(start, stop, state_at(problem, work_kf, start), FIRST_STREAM + 2 * best.rounds)
        kf, band_logs = optimise_windows(problem, repair_settings(settings, widened), work_kf, progress,
                                         should_stop, band=band)
        best.rounds += 1
        best.evaluations += int(sum(w.evaluations for w in band_logs))
        m = score(kf)
        by_index = {w.index: w for w in band_logs}
        logs_now = [by_index.get(w.index, w) for w in work_logs]
        after = first_past_limit(m["per_frame"])
        if repair_rank(m) > repair_rank(best.metrics):
            best.keyframes, best.metrics, best.logs, best.kept = kf, m, logs_now, best.kept + 1
            work_kf, work_m, work_logs, widened = kf, m, logs_now, False
        elif after is not None and after > fail:
            # The band held the object past where it failed, and the later keyframes, chosen for the attempt's
            # state there, lose it further on: the next band chases that failure from this one's keyframes.
            work_kf, work_m, work_logs, widened = kf, m, logs_now, False
        elif widened:
            break
        else:
            work_kf, work_m, work_logs, widened = best.keyframes, best.metrics, best.logs, True
    return best
