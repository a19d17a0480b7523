"""The attempts of a refinement (``worker.refine.run``): which ways they run and when they stop."""

from __future__ import annotations

import pytest

from worker.refine.replay import LOOKAHEAD_ROTATION_WEIGHT
from worker.refine.run import RETRY_OBJECT_ERROR, attempt_plan, attempt_seed, attempts_done, object_error


def test_the_first_attempt_leaves_the_lookahead_rotation_out_and_the_later_ones_are_the_earlier_restarts() -> None:
    plan = [attempt_plan(5, k) for k in range(4)]
    # After the first, the attempts the product made before the lookahead rotation discount: full loss, the
    # job's seed, then the restart seeds.
    assert plan == [(5, LOOKAHEAD_ROTATION_WEIGHT), (5, 1.0), (attempt_seed(5, 1), 1.0), (attempt_seed(5, 2), 1.0)]
    assert LOOKAHEAD_ROTATION_WEIGHT != 1.0


def test_the_retry_level_is_the_published_mean_object_error() -> None:
    # 0.67 cm and 2.97 deg (the Grasp-and-Lift paper's DexYCB means) in the object_pose loss's units.
    assert object_error({"E_t": 0.67, "E_r": 2.97}) == pytest.approx(RETRY_OBJECT_ERROR)


def test_a_poor_first_success_is_tried_again_and_a_failure_always() -> None:
    good = {"success": True, "E_t": 0.4, "E_r": 1.5}
    poor = {"success": True, "E_t": 1.0, "E_r": 4.0}
    failed = {"success": False, "E_t": 0.4, "E_r": 1.5}
    assert attempts_done(good, 0)
    assert not attempts_done(poor, 0)  # a success worse than the published mean: the other way too
    assert attempts_done(poor, 1)  # after the second attempt any success stops
    assert not attempts_done(failed, 0) and not attempts_done(failed, 3)
