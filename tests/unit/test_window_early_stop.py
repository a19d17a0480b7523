"""A window's CMA-ES stops when its best loss stalls (worker.refine.windowed, ``stall_generations``; issue #19)."""

from __future__ import annotations

from typing import Any

import numpy as np

from worker.refine.windowed import CmaSettings, _stalled, optimise_windows


class Bowl:
    """A window problem without physics: keyframe j's loss is its squared distance to ``target``."""

    sides: tuple[str, ...] = ("right",)
    n_keyframes = 3
    first_window = 1

    def __init__(self, target: np.ndarray) -> None:
        self.target = target

    def dim(self, side: str) -> int:
        return len(self.target)

    def start_state(self) -> Any:
        return None

    def probe(self, j: int, state: Any, keyframes: dict[str, np.ndarray]) -> tuple[dict[str, float], bool]:
        return {"right": float(np.sum((keyframes["right"][j] - self.target) ** 2))}, True

    def evaluate(self, j: int, state: Any, keyframes: dict[str, np.ndarray], candidates: dict[str, np.ndarray],
                 hold: bool = True
                 ) -> dict[str, np.ndarray]:
        return {"right": np.sum((candidates["right"] - self.target) ** 2, axis=1)}

    def commit(self, j: int, state: Any, keyframes: dict[str, np.ndarray]) -> Any:
        return None


def _settings(stall: int) -> CmaSettings:
    return CmaSettings(popsize=6, max_generations=12, skip_loss=0.0, seed=3, stall_generations=stall)


def test_a_window_already_at_its_optimum_stops_after_the_stall_span() -> None:
    # The warm start is the optimum itself: no candidate can beat it, the best loss is flat from generation 1.
    _, logs = optimise_windows(Bowl(np.zeros(4)), _settings(stall=3))
    assert all(w.stopped_early for w in logs)
    assert all(len(w.history) == 4 and w.evaluations == 1 + 6 * 4 for w in logs)
    assert all(w.best_loss == 0.0 for w in logs)


def test_a_window_still_improving_runs_every_generation() -> None:
    # Far from the bowl's bottom each generation improves the best loss by far more than 1 %.
    _, logs = optimise_windows(Bowl(np.full(4, 2.5)), _settings(stall=3))
    first = logs[0]
    assert not first.stopped_early and len(first.history) == 12


def test_no_early_stop_by_default() -> None:
    _, logs = optimise_windows(Bowl(np.zeros(4)), _settings(stall=0))
    assert not any(w.stopped_early for w in logs) and all(len(w.history) == 12 for w in logs)


def test_stalled_compares_the_best_loss_over_the_span() -> None:
    settings = CmaSettings(stall_generations=2, stall_tolerance=0.01)
    assert not _stalled([10.0, 9.0], settings)  # not enough generations yet
    assert not _stalled([10.0, 9.0, 8.0], settings)  # 20 % better over 2 generations
    assert _stalled([10.0, 9.95, 9.92], settings)  # 0.8 % better: stalled
    assert _stalled([5.0, 5.0, 5.0], settings)


def test_a_stalled_window_still_far_off_keeps_searching() -> None:
    # The bowl's bottom lies outside the bounds: the best loss stalls at the bound, far above stall_below.
    settings = CmaSettings(popsize=6, max_generations=12, skip_loss=0.0, seed=3, stall_generations=3,
                           stall_below=1.0, bound=1.0)
    _, logs = optimise_windows(Bowl(np.full(4, 10.0)), settings)
    assert not any(w.stopped_early for w in logs) and all(len(w.history) == 12 for w in logs)
    assert _stalled([0.5, 0.5, 0.5, 0.5], settings)  # the same flat history below the level stops
    assert not _stalled([81.0, 81.0, 81.0, 81.0], settings)
