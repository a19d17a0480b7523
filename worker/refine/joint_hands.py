"""Both hands' keyframes under one CMA-ES (issue #52 item 4), the alternative to the paper's one CMA-ES per hand.

The paper's two-hand refinement (its OakInk-V2 experiment) runs a CMA-ES per hand, their candidates paired in the
same rollouts, each told its own objective (the object's terms plus its hand's; ``windowed``). Paired that way, a
hand's candidate is scored beside a random candidate of the other hand, so what it sees of the object is noisy
where the two hands hold it together. ``JointHandsProblem`` presents the two hands' keyframes as one vector
(right then left, as ``problem.sides`` orders them) to a single CMA-ES that minimises one objective: the object's
terms once plus both hands' terms (``SimWindowProblem.combined``). ``TWO_HAND_MODES`` names the two ways; which is
the default is decided on the real two-hand sequences (``bench/results/refine_arctic.md``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from common.geometry import FloatArray
from worker.refine.problem import COMBINED, SimWindowProblem

TWO_HAND_MODES = ("per_hand", "joint")


class JointHandsProblem:
    """A ``windowed.WindowProblem`` over a two-hand ``SimWindowProblem`` with one stacked keyframe vector."""

    def __init__(self, inner: SimWindowProblem) -> None:
        self.inner = inner
        inner.combined = True
        self.hand_sides = inner.sides
        self.sides: tuple[str, ...] = (COMBINED,)
        self.n_keyframes = inner.n_keyframes
        self.first_window = inner.first_window
        self._dims = [inner.dim(s) for s in self.hand_sides]

    def dim(self, side: str) -> int:
        return sum(self._dims)

    def split(self, stacked: FloatArray) -> dict[str, FloatArray]:
        """Each hand's part of stacked keyframes or candidates (..., sum of dims)."""
        cuts = np.cumsum(self._dims)[:-1]
        return dict(zip(self.hand_sides, np.split(stacked, cuts, axis=-1), strict=True))

    def stack(self, per_hand: dict[str, FloatArray]) -> dict[str, FloatArray]:
        return {COMBINED: np.concatenate([per_hand[s] for s in self.hand_sides], axis=-1)}

    def start_state(self) -> Any:
        return self.inner.start_state()

    def probe(self, j: int, state: Any, keyframes: dict[str, FloatArray]) -> tuple[dict[str, float], bool]:
        return self.inner.probe(j, state, self.split(keyframes[COMBINED]))

    def evaluate(self, j: int, state: Any, keyframes: dict[str, FloatArray], candidates: dict[str, FloatArray],
                 hold: bool = True) -> dict[str, FloatArray]:
        return self.inner.evaluate(j, state, self.split(keyframes[COMBINED]), self.split(candidates[COMBINED]), hold)

    def commit(self, j: int, state: Any, keyframes: dict[str, FloatArray]) -> Any:
        return self.inner.commit(j, state, self.split(keyframes[COMBINED]))
