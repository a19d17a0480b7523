"""The lease heartbeat thread: cadence, progress forwarding, cancel / lost-lease / stop signals."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest

from common.errors import LeaseLostError
from worker.runtime.heartbeat import Heartbeat


class Recorder:
    """A renew function with a scripted answer per call (a real callable, not a database stand-in)."""

    def __init__(self, answers: list[Any] | None = None) -> None:
        self.calls: list[tuple[float, dict[str, Any] | None, str]] = []
        self.answers = list(answers or [])

    def __call__(self, progress: dict[str, Any] | None) -> bool:
        self.calls.append((time.monotonic(), progress, threading.current_thread().name))
        answer = self.answers.pop(0) if self.answers else False
        if isinstance(answer, BaseException):
            raise answer
        return bool(answer)


def test_renews_at_the_interval_from_its_own_thread_with_latest_progress() -> None:
    rec = Recorder()
    hb = Heartbeat(rec, interval=0.05, base_progress={"pid": 1})
    with hb:
        hb.update({"window": 1})
        time.sleep(0.18)
        hb.update({"window": 2, "best_loss": 0.5})
        time.sleep(0.12)
    n = len(rec.calls)
    assert 4 <= n <= 7, n
    assert all(name == "hoi-refine-heartbeat" for _, _, name in rec.calls)
    assert rec.calls[0][1] == {"pid": 1, "window": 1}
    assert rec.calls[-1][1] == {"pid": 1, "window": 2, "best_loss": 0.5}
    gaps = [b[0] - a[0] for a, b in zip(rec.calls, rec.calls[1:], strict=False)]
    assert min(gaps) > 0.03
    time.sleep(0.1)
    assert len(rec.calls) == n  # stopped: no more renewals
    assert not hb.should_stop()


def test_cancel_flag_makes_should_stop_true() -> None:
    hb = Heartbeat(Recorder([False, True]), interval=0.02)
    with hb:
        deadline = time.monotonic() + 2
        while not hb.should_stop() and time.monotonic() < deadline:
            time.sleep(0.005)
    assert hb.cancel_requested and not hb.lease_lost and not hb.stop_requested


def test_lost_lease_stops_the_thread_and_is_reported() -> None:
    rec = Recorder([False, LeaseLostError("gone")])
    hb = Heartbeat(rec, interval=0.02).start()
    time.sleep(0.2)
    assert hb.lease_lost and hb.should_stop()
    assert len(rec.calls) == 2  # no renewal after the loss
    hb.stop()


def test_transient_errors_are_retried_until_the_lease_has_surely_expired() -> None:
    rec = Recorder([RuntimeError("db down"), True])
    hb = Heartbeat(rec, interval=0.02, lease_seconds=10)
    hb.beat()
    assert not hb.should_stop()  # one failed renewal is not a lost lease
    hb.beat()
    assert hb.cancel_requested and hb.renewals == 1

    now = [0.0]
    failing = Recorder([RuntimeError("db down")] * 3)
    hb2 = Heartbeat(failing, interval=1, lease_seconds=3, clock=lambda: now[0])
    hb2.beat()
    now[0] = 2.0
    hb2.beat()
    assert not hb2.lease_lost
    now[0] = 3.5
    hb2.beat()
    assert hb2.lease_lost


def test_request_stop_and_prompt_shutdown() -> None:
    hb = Heartbeat(Recorder(), interval=30).start()
    hb.request_stop()
    assert hb.should_stop() and hb.stop_requested and not hb.cancel_requested
    t0 = time.monotonic()
    hb.stop()
    assert time.monotonic() - t0 < 1.0  # does not wait out the 30 s interval


def test_rejects_a_non_positive_interval() -> None:
    with pytest.raises(ValueError, match="interval"):
        Heartbeat(Recorder(), interval=0)
