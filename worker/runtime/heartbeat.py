"""The lease heartbeat: renews a job's lease from its own thread while the compute loop runs.

DESIGN §2 ("a per-job lease renewed from a thread that is not the compute loop"): the refinement may hold
the GIL-free MuJoCo rollouts for seconds at a time, so the lease must not depend on the optimiser reaching
a checkpoint. The thread renews every ``interval`` seconds (lease / 3 by default, so two renewals may fail
before the lease expires), sends the latest progress with each renewal, and records what the queue says
back: a cancellation request or a lost lease. The compute loop polls ``should_stop()`` once per CMA-ES
generation, which bounds the time to stop after a cancel to one renewal interval plus one generation.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from common.errors import LeaseLostError

log = logging.getLogger(__name__)

#: ``renew(progress) -> cancel_requested``; raises ``LeaseLostError`` when the lease is gone.
RenewFn = Callable[[dict[str, Any] | None], bool]


class Heartbeat:
    """Renews one job's lease every ``interval`` seconds until ``stop()``.

    Other errors than ``LeaseLostError`` (database briefly unreachable) are logged and retried at the
    next tick: the lease is only lost when the queue says so or when it has certainly expired.
    """

    def __init__(
        self,
        renew: RenewFn,
        interval: float,
        lease_seconds: float | None = None,
        base_progress: dict[str, Any] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not interval > 0:
            raise ValueError(f"interval must be > 0 seconds, got {interval}")
        self._renew = renew
        self._interval = float(interval)
        self._lease_seconds = lease_seconds
        self._clock = clock
        self._lock = threading.Lock()
        self._base: dict[str, Any] = dict(base_progress or {})
        self._progress: dict[str, Any] = dict(self._base)
        self._stopped = threading.Event()
        self._cancel = threading.Event()
        self._lost = threading.Event()
        self._external_stop = threading.Event()
        self._last_ok = clock()
        self._renewals = 0
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ state read by the compute loop

    @property
    def cancel_requested(self) -> bool:
        return self._cancel.is_set()

    @property
    def lease_lost(self) -> bool:
        return self._lost.is_set()

    @property
    def stop_requested(self) -> bool:
        """The worker itself is shutting down (graceful stop, not a cancel)."""
        return self._external_stop.is_set()

    @property
    def renewals(self) -> int:
        return self._renewals

    def should_stop(self) -> bool:
        """True once a cancel was seen, the lease was lost, or ``request_stop()`` was called."""
        return self._cancel.is_set() or self._lost.is_set() or self._external_stop.is_set()

    def request_stop(self) -> None:
        self._external_stop.set()

    def update(self, progress: dict[str, Any]) -> None:
        """Merge the compute loop's latest progress; it is sent with the next renewal. A whole-job document (it
        has a ``step``, ``common.progress``) replaces the previous one instead, over the base keys, so that a
        pass's keys (a polish sweep's number, the windows) do not outlive it."""
        with self._lock:
            if "step" in progress:
                self._progress = {**self._base, **progress}
            else:
                self._progress.update(progress)

    def progress(self) -> dict[str, Any]:
        with self._lock:
            return dict(self._progress)

    # ------------------------------------------------------------------ thread

    def beat(self) -> None:
        """One renewal (the thread calls this; tests may call it directly)."""
        try:
            cancel = self._renew(self.progress())
        except LeaseLostError as exc:
            log.warning("lease lost: %s", exc)
            self._lost.set()
            return
        except Exception as exc:  # database hiccup: keep trying until the lease has surely expired
            log.warning("heartbeat failed (%s: %s); retrying in %.1f s", type(exc).__name__, exc, self._interval)
            if self._lease_seconds is not None and self._clock() - self._last_ok > self._lease_seconds:
                log.warning("no successful heartbeat for %.1f s: assuming the lease is lost", self._lease_seconds)
                self._lost.set()
            return
        self._last_ok = self._clock()
        self._renewals += 1
        if cancel and not self._cancel.is_set():
            log.info("cancellation requested")
            self._cancel.set()

    def _run(self) -> None:
        while not self._stopped.wait(self._interval):
            self.beat()
            if self._lost.is_set():
                return

    def start(self) -> Heartbeat:
        if self._thread is not None:
            raise RuntimeError("heartbeat already started")
        self._last_ok = self._clock()
        self._thread = threading.Thread(target=self._run, name="hoi-refine-heartbeat", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float | None = None) -> None:
        """Stop renewing and wait for the thread (an in-flight renewal finishes first)."""
        self._stopped.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def __enter__(self) -> Heartbeat:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
