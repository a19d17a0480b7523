"""A first pass goes back when a window stands out (worker.refine.windowed, ``rewind_windows``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from worker.refine.windowed import CmaSettings, WindowLog, optimise_windows


class StepsProblem:
    """A window problem without physics where a window can be hopeless because of what earlier windows committed.

    Each window chooses a step of +1 or -1 from the keyframe committed before it (two equal wells; the warm start sits
    on the ridge between them, so the random stream decides). Window HARD costs 100 more unless the position it
    starts from is above 0: a path that went down first loses it for good, as a grasp lost a window early does.
    """

    sides: tuple[str, ...] = ("right",)
    n_keyframes = 9
    first_window = 1
    HARD = 6

    def dim(self, side: str) -> int:
        return 2

    def start_state(self) -> Any:
        return (0.0,)

    def _loss(self, j: int, state: tuple[float, ...], x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(x)
        step = x[:, 0] - state[-1]
        loss = 10 * (step**2 - 1) ** 2 + x[:, 1] ** 2
        return loss + 100.0 if j == self.HARD and state[-1] <= 0 else loss

    def probe(self, j: int, state: Any, keyframes: dict[str, np.ndarray]) -> tuple[dict[str, float], bool]:
        return {"right": float(self._loss(j, state, keyframes["right"][j])[0])}, True

    def evaluate(self, j: int, state: Any, keyframes: dict[str, np.ndarray], candidates: dict[str, np.ndarray],
                 hold: bool = True) -> dict[str, np.ndarray]:
        return {"right": self._loss(j, state, candidates["right"])}

    def commit(self, j: int, state: Any, keyframes: dict[str, np.ndarray]) -> Any:
        return (*state, float(keyframes["right"][j, 0]))


def _run(seed: int, rewind_windows: int) -> tuple[np.ndarray, list[WindowLog]]:
    settings = CmaSettings(popsize=6, max_generations=4, skip_loss=0.0, seed=seed, escalate_loss=5.0,
                           rewind_windows=rewind_windows)
    kf, logs = optimise_windows(StepsProblem(), settings)
    return kf["right"], logs


def test_a_window_lost_by_earlier_commits_is_won_back_by_running_them_again() -> None:
    _, plain = _run(10, 0)  # this seed's first pass goes down early and loses window HARD
    kf, logs = _run(10, 2)

    assert plain[StepsProblem.HARD - 1].best_loss > 100
    assert [w.index for w in logs] == list(range(1, 9))  # one log per window, in order
    hard = logs[StepsProblem.HARD - 1]
    assert hard.rewound and hard.best_loss < 10
    assert [w.index for w in logs if w.rewound] == [StepsProblem.HARD]
    assert kf[StepsProblem.HARD - 1, 0] > 0  # the rewound windows chose another path
    # Both runs of the rewound windows are paid for.
    assert sum(w.evaluations for w in logs) > sum(w.evaluations for w in plain)


def test_a_rewind_that_does_no_better_keeps_the_first_run() -> None:
    plain_kf, plain = _run(3, 0)  # this seed's rewind finds no better path
    kf, logs = _run(3, 2)

    np.testing.assert_array_equal(kf, plain_kf)
    assert [w.best_loss for w in logs] == [w.best_loss for w in plain]
    rewound = [i for i, w in enumerate(logs) if w.rewound]
    assert rewound == [StepsProblem.HARD - 1]
    extra = logs[rewound[0]].evaluations - plain[rewound[0]].evaluations
    assert extra >= 3 * 6  # the discarded run of three windows, counted on the window that stood out


def test_no_rewind_without_a_standout_or_when_switched_off() -> None:
    for seed in (0, 4):  # paths that stay up: nothing stands out
        assert not any(w.rewound for w in _run(seed, 2)[1])
    assert not any(w.rewound for w in _run(10, 0)[1])


def test_rewinds_are_deterministic() -> None:
    a, b = _run(10, 2), _run(10, 2)
    np.testing.assert_array_equal(a[0], b[0])
    assert [w.history for w in a[1]] == [w.history for w in b[1]]
