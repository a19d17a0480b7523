"""SIGINT and SIGTERM as a request to stop: a long-running command winds down in order instead of being torn
down by a KeyboardInterrupt in the middle of a write."""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType


@contextmanager
def stop_on_signals(stop: threading.Event, on_signal: Callable[[signal.Signals, bool], None]) -> Iterator[None]:
    """While inside, SIGINT and SIGTERM set ``stop`` and call ``on_signal(signal, again)`` (``again``: ``stop`` was
    already set; it may raise to abort); the previous handlers come back on exit. The handlers are the command's own,
    so it also stops where it was started with SIGINT ignored (a background job of a non-interactive shell). Only the
    main thread can install handlers; elsewhere (a test's thread) nothing is installed and ``stop`` is the only way."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, _frame: FrameType | None) -> None:
        again = stop.is_set()
        stop.set()
        on_signal(signal.Signals(signum), again)

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
