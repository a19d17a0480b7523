"""The polish sweep (worker.refine.windowed ``polish=True``, worker.refine.controls ``hold=False``): each window
replaces its own keyframe only, against the later keyframes of the finished pass."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from worker.refine.controls import HandControlSpace, PoseBasis10
from worker.refine.run import POLISH_OBJECT_ERROR, POLISH_SIGMA_FACTOR, RETRY_OBJECT_ERROR, polish_settings
from worker.refine.windowed import CmaSettings, optimise_windows

TARGETS = np.array([[0.0, 0.0], [1.0, -1.0], [2.0, 0.5], [-1.0, 1.5], [0.5, 0.5]])


class CoupledProblem:
    """A window problem without physics whose window j is scored on keyframes j and j + 1, as a window's lookahead
    is: (x_j - T_j)^2 + (x_{j+1} - T_{j+1})^2, x_{j+1} being the candidate when held and the given keyframe when not.
    It records what each evaluation was given."""

    sides: tuple[str, ...] = ("right",)
    n_keyframes = 5
    first_window = 1

    def __init__(self) -> None:
        self.calls: list[tuple[int, bool, np.ndarray]] = []

    def dim(self, side: str) -> int:
        return 2

    def start_state(self) -> Any:
        return None

    def _loss(self, j: int, here: np.ndarray, after: np.ndarray) -> np.ndarray:
        loss = np.sum((here - TARGETS[j]) ** 2, axis=-1)
        if j + 1 < self.n_keyframes:
            loss = loss + np.sum((after - TARGETS[j + 1]) ** 2, axis=-1)
        return np.asarray(loss)

    def probe(self, j: int, state: Any, keyframes: dict[str, np.ndarray]) -> tuple[dict[str, float], bool]:
        kf = keyframes["right"]
        after = kf[j + 1] if j + 1 < self.n_keyframes else kf[j]
        return {"right": float(self._loss(j, kf[j], after))}, True

    def evaluate(self, j: int, state: Any, keyframes: dict[str, np.ndarray], candidates: dict[str, np.ndarray],
                 hold: bool = True) -> dict[str, np.ndarray]:
        self.calls.append((j, hold, keyframes["right"].copy()))
        c = candidates["right"]
        held = hold or j + 1 >= self.n_keyframes
        after = c if held else np.broadcast_to(keyframes["right"][j + 1], c.shape)
        return {"right": self._loss(j, c, after)}

    def commit(self, j: int, state: Any, keyframes: dict[str, np.ndarray]) -> Any:
        return None


SETTINGS = CmaSettings(popsize=6, max_generations=6, skip_loss=0.0, seed=3)


def test_a_polish_needs_the_keyframes_of_a_finished_pass() -> None:
    with pytest.raises(ValueError, match="finished pass"):
        optimise_windows(CoupledProblem(), SETTINGS, polish=True)


def test_the_polish_replaces_one_keyframe_per_window_and_sees_the_later_ones() -> None:
    first = CoupledProblem()
    kf, _ = optimise_windows(first, SETTINGS)
    assert all(hold for _, hold, _ in first.calls)
    given = kf["right"].copy()
    problem = CoupledProblem()
    polished, logs = optimise_windows(problem, SETTINGS, kf, polish=True)
    np.testing.assert_array_equal(kf["right"], given)  # the finished pass's keyframes are not written to
    assert problem.calls and not any(hold for _, hold, _ in problem.calls)
    for j, _, seen in problem.calls:
        # Window j sees the finished pass's later keyframes, not a candidate held over them, and the polished
        # earlier ones.
        np.testing.assert_array_equal(seen[j + 1:], given[j + 1:])
        np.testing.assert_array_equal(seen[1:j], polished["right"][1:j])
    np.testing.assert_array_equal(polished["right"][0], given[0])  # before first_window: untouched
    for log in logs:  # a window's best starts at the given keyframe, so the polish never makes it worse
        assert log.best_loss <= log.initial_loss


def test_a_polish_of_keyframes_already_at_their_optimum_leaves_them() -> None:
    kf = {"right": TARGETS.copy()}
    polished, logs = optimise_windows(CoupledProblem(), SETTINGS, kf, polish=True)
    np.testing.assert_array_equal(polished["right"], TARGETS)
    assert all(log.best_loss == 0.0 for log in logs)


def test_offsets_without_hold_replace_keyframe_j_alone() -> None:
    frames, substeps = 21, 8
    identity = np.tile([1.0, 0, 0, 0], (frames, 1))
    space = HandControlSpace("right", np.zeros((frames, 2)), np.zeros((frames, 3)), identity,
                             np.array([[-1.0, 1], [-1, 1]]), PoseBasis10(np.zeros((10, 2)), np.ones(10)), interval=5,
                             substeps=substeps)
    rng = np.random.default_rng(4)
    keyframes = rng.normal(size=(space.n_keyframes, space.dim))
    candidates = rng.normal(size=(3, space.dim))
    idx = np.arange(frames) * substeps
    j = 2
    replaced = space.offsets(keyframes, idx, j, candidates, hold=False)
    for c in range(3):
        one = keyframes.copy()
        one[j] = candidates[c]
        np.testing.assert_allclose(replaced[c], space.offsets(one, idx)[0], atol=1e-12)
    held = space.offsets(keyframes, idx, j, candidates)  # the first pass's: keyframe j and every later one
    one = keyframes.copy()
    one[j:] = candidates[0]
    np.testing.assert_allclose(held[0], space.offsets(one, idx)[0], atol=1e-12)


def test_polish_settings_search_nearer_and_never_escalate() -> None:
    base = CmaSettings(sigma0=0.5, escalate_loss=30.0, seed=7, popsize=10)
    polish = polish_settings(base)
    assert polish.sigma0 == 0.5 * POLISH_SIGMA_FACTOR < base.sigma0
    assert polish.escalate_loss == float("inf")
    assert (polish.seed, polish.popsize) == (7, 10)
    assert POLISH_OBJECT_ERROR < RETRY_OBJECT_ERROR
