"""Hard windows get a second, larger CMA-ES run (worker.refine.windowed, ``escalate_loss``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from worker.refine.windowed import CmaSettings, optimise_windows

TARGET = np.array([2.0, -1.5, 1.0])


class BowlProblem:
    """A window problem without physics: keyframe j's loss is its squared distance to TARGET (scaled)."""

    sides: tuple[str, ...] = ("right",)
    n_keyframes = 4
    first_window = 1

    def dim(self, side: str) -> int:
        return 3

    def start_state(self) -> Any:
        return None

    def probe(self, j: int, state: Any, keyframes: dict[str, np.ndarray]) -> tuple[dict[str, float], bool]:
        return {"right": float(10 * np.sum((keyframes["right"][j] - TARGET) ** 2))}, True

    def evaluate(self, j: int, state: Any, keyframes: dict[str, np.ndarray], candidates: dict[str, np.ndarray],
                 hold: bool = True
                 ) -> dict[str, np.ndarray]:
        return {"right": 10 * np.sum((candidates["right"] - TARGET) ** 2, axis=1)}

    def commit(self, j: int, state: Any, keyframes: dict[str, np.ndarray]) -> Any:
        return None


def _run(escalate_loss: float) -> tuple[dict[str, np.ndarray], list[Any]]:
    settings = CmaSettings(popsize=4, max_generations=2, skip_loss=0.0, seed=5, escalate_loss=escalate_loss)
    return optimise_windows(BowlProblem(), settings)


def test_a_window_left_above_the_threshold_gets_a_larger_second_run() -> None:
    _, plain = _run(float("inf"))
    kf, escalated = _run(1.0)
    first = plain[0]
    assert not first.escalated and first.evaluations == 1 + 4 * 2
    assert first.best_loss > 1.0  # 8 evaluations from 0 cannot reach the bowl at distance 2.7
    hard = escalated[0]
    assert hard.escalated and hard.evaluations == 1 + 4 * 2 + 8 * 2  # the second run doubles the population
    assert hard.best_loss < first.best_loss
    assert len(hard.history) == 4  # both runs' generations are in the loss history
    # The second run starts where the first ended, and later windows start from the better keyframe.
    assert np.sum((kf["right"][1] - TARGET) ** 2) * 10 == hard.best_loss
    assert all(w.best_loss <= p.best_loss for w, p in zip(escalated, plain, strict=True))


def test_escalation_is_deterministic() -> None:
    kf1, logs1 = _run(1.0)
    kf2, logs2 = _run(1.0)
    np.testing.assert_array_equal(kf1["right"], kf2["right"])
    assert [w.history for w in logs1] == [w.history for w in logs2]
