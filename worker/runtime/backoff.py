"""Retry a database call with exponential backoff while the database is unreachable (issue #5.1).

A worker must outlive a database restart: it keeps trying, says so in its log once per attempt, and
resumes as soon as the database answers. Only connection-level failures are retried here; a query that
the database rejects (a bug, a constraint) is raised at once.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import sqlalchemy as sa

from common.errors import DatabaseUnavailableError, HoiRefineError

T = TypeVar("T")
log = logging.getLogger(__name__)


class WorkerStopping(HoiRefineError):
    """The worker was asked to stop while it waited for the database."""


def is_unreachable(exc: BaseException) -> bool:
    """True for errors that mean "the database is not answering" (worth waiting for)."""
    if isinstance(exc, DatabaseUnavailableError):
        return True
    if isinstance(exc, sa.exc.DBAPIError) and exc.connection_invalidated:
        return True
    return isinstance(exc, sa.exc.OperationalError | sa.exc.InterfaceError | sa.exc.TimeoutError)


@dataclass
class Backoff:
    """Delays first, 2·first, 4·first, ... capped at ``maximum`` seconds."""

    first: float = 0.5
    maximum: float = 30.0

    def delays(self) -> Callable[[], float]:
        state = {"next": self.first}

        def step() -> float:
            delay = state["next"]
            state["next"] = min(delay * 2.0, self.maximum)
            return delay

        return step


def call_with_backoff(
    fn: Callable[[], T],
    what: str,
    backoff: Backoff,
    stop: threading.Event | None = None,
    logger: logging.Logger = log,
) -> T:
    """``fn()``, retried while the database is unreachable; raises ``WorkerStopping`` if ``stop`` is set."""
    next_delay = backoff.delays()
    failures = 0
    while True:
        try:
            result = fn()
        except Exception as exc:
            if not is_unreachable(exc):
                raise
            failures += 1
            delay = next_delay()
            logger.warning(
                "database unreachable during %s (%s: %s); retry %d in %.1f s",
                what,
                type(exc).__name__,
                str(exc).splitlines()[0][:200] if str(exc) else "",
                failures,
                delay,
            )
            if stop is not None:
                if stop.wait(delay):
                    raise WorkerStopping(f"stopped while waiting for the database ({what})") from exc
            else:
                threading.Event().wait(delay)
            continue
        if failures:
            logger.info("database reachable again after %d failed attempt(s) (%s)", failures, what)
        return result
