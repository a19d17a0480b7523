"""common.stop_signals: SIGINT / SIGTERM set the stop event, tell the command whether it is the second, and the
previous handlers come back."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from common.stop_signals import stop_on_signals


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_each_signal_sets_stop_and_says_whether_it_came_again(sig: signal.Signals) -> None:
    stop, heard = threading.Event(), []
    before = signal.getsignal(sig)
    with stop_on_signals(stop, lambda s, again: heard.append((s, again))):
        os.kill(os.getpid(), sig)
        os.kill(os.getpid(), sig)
    assert stop.is_set()
    assert heard == [(sig, False), (sig, True)]
    assert signal.getsignal(sig) is before


def test_a_callback_that_raises_aborts_the_command() -> None:
    def abort(_sig: signal.Signals, again: bool) -> None:
        if again:
            raise KeyboardInterrupt

    stop = threading.Event()
    with pytest.raises(KeyboardInterrupt), stop_on_signals(stop, abort):
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.is_set()
        os.kill(os.getpid(), signal.SIGINT)


def test_outside_the_main_thread_nothing_is_installed() -> None:
    seen: list[object] = []

    def in_thread() -> None:
        with stop_on_signals(threading.Event(), lambda s, a: None):
            seen.append(signal.getsignal(signal.SIGINT))

    before = signal.getsignal(signal.SIGINT)
    thread = threading.Thread(target=in_thread)
    thread.start()
    thread.join()
    assert seen == [before]
