"""A robot hand's joint speed limits (issue #55: an executable trajectory): the retargeted motion brought within
them (``worker.robot.speed``), the ``robot_speed`` loss term, and the metrics and outcome that say when a robot's
motion exceeds them."""

from __future__ import annotations

import numpy as np

from common.outcome import FAILURE_CODES, Outcome, ReasonCode
from worker.refine.losses import resolve_weights, speed_excess
from worker.refine.outcome import robot_too_fast
from worker.robot.metrics import robot_motion_metrics
from worker.robot.speed import SPEED_FRACTION, speed_limited, step_ratio

FPS = 30.0


def _closing(frames: int = 80) -> np.ndarray:
    """(frames, 3): a fast grasp closing 1.5 rad in ~0.2 s, a slow joint, and one with no limit."""
    t = np.arange(frames) / FPS
    fast = 1.5 / (1.0 + np.exp(-(t - 1.3) * 25.0))
    return np.stack([fast, 0.1 * np.sin(t), fast], axis=1)


def test_speed_limited_keeps_each_step_within_the_limit_and_the_rest_as_it_was() -> None:
    q = _closing()
    vmax = np.array([3.14, 3.14, np.inf])
    limits = np.array([[0.0, 1.5], [-1.0, 1.0], [0.0, 1.5]])
    assert (step_ratio(q, vmax, FPS) or 0.0) > 2.0
    out = speed_limited(q, vmax, FPS, limits)
    assert np.abs(np.diff(out[:, 0])).max() <= SPEED_FRACTION * 3.14 / FPS + 1e-12
    assert (out[:, 1:] == q[:, 1:]).all()  # within its limit / no limit: bit for bit
    assert (out[:, 0] >= 0.0).all() and (out[:, 0] <= 1.5).all()
    # The closest such track: it starts earlier and ends later, centred on the fast part, and beats the causal
    # rate limiter (which only lags) in least squares.
    assert out[34, 0] > q[34, 0] + 0.05 and out[44, 0] < q[44, 0] - 0.05
    bound = SPEED_FRACTION * 3.14 / FPS
    lag = np.empty(len(q))
    lag[0] = q[0, 0]
    for i in range(1, len(q)):
        lag[i] = lag[i - 1] + np.clip(q[i, 0] - lag[i - 1], -bound, bound)
    assert np.sum((out[:, 0] - q[:, 0]) ** 2) < np.sum((lag - q[:, 0]) ** 2)
    assert (step_ratio(out, vmax, FPS) or np.inf) <= SPEED_FRACTION + 1e-9
    assert step_ratio(q, np.full(3, np.inf), FPS) is None


def test_the_robot_speed_term_is_zero_within_the_limit_and_one_at_ten_percent_over_for_a_frame() -> None:
    step = np.array([0.1, 0.1])
    within = np.cumsum(np.full((1, 5, 2), 0.09), axis=1)
    assert speed_excess(within, step)[0] == 0.0
    once = within.copy()
    once[0, 3:, 0] += 0.02  # one step of 0.11 on joint 0
    assert np.isclose(speed_excess(once, step)[0], 1.0)
    assert speed_excess(once, np.array([np.inf, np.inf]))[0] == 0.0
    # The human hand's weights have no robot terms: its results stay as they were.
    assert "robot_speed" not in resolve_weights(None) and resolve_weights(None, robot=True)["robot_speed"] > 0


def test_the_metrics_and_the_outcome_say_when_a_robot_exceeds_its_speed_limits() -> None:
    q = _closing()
    limits = np.array([[0.0, 1.5], [-1.0, 1.0], [0.0, 1.5]])
    force = np.zeros_like(q)
    vmax = np.array([3.14, 3.14, 3.14])
    fast = robot_motion_metrics(q, q, force, limits, vmax, np.full(3, 1.0), FPS)
    assert fast["speed_limit_exceeded"] and fast["velocity_ratio"] > 2.0
    assert abs(fast["speed_limit_frame"] - 39) <= 2  # the closing's middle
    slow_q = speed_limited(q, vmax, FPS, limits)
    slow = robot_motion_metrics(slow_q, slow_q, force, limits, vmax, np.full(3, 1.0), FPS)
    assert slow["speed_limit_exceeded"] is False and slow["speed_limit_frame"] is None
    unknown = robot_motion_metrics(q, q, force, limits, np.full(3, np.inf), np.full(3, 1.0), FPS)
    assert unknown["speed_limit_exceeded"] is None and unknown["velocity_ratio"] is None

    reasons = robot_too_fast({"robot": {"right": fast, "left": slow}})
    assert [r.code for r in reasons] == [ReasonCode.ROBOT_TOO_FAST]
    (reason,) = reasons
    assert reason.unit == "ratio" and reason.frame == fast["speed_limit_frame"] and (reason.value or 0.0) > 2.0
    assert "right robot hand" in reason.message
    # Informative: an executable result carries it, and it is never the failure's primary reason.
    outcome = Outcome(executable=True, reasons=reasons)
    assert ReasonCode.ROBOT_TOO_FAST not in FAILURE_CODES and outcome.primary() is None
    assert Outcome.model_validate(outcome.model_dump(mode="json")) == outcome
    assert robot_too_fast({"paper": {}}) == []  # the human hand has no robot metrics
