"""The refinement's progress line on stderr, shared by ``refine`` and the in-process ``demo``."""

from __future__ import annotations

import sys
from typing import Any


class ProgressBar:
    """Window i/N, best loss, evaluations, ETA: one rewritten line on a terminal; in a log (not a TTY), one
    line per finished window instead of hundreds of carriage-return updates."""

    def __init__(self) -> None:
        self._tty = sys.stderr.isatty()
        self._last_window = (0, -1)

    def __call__(self, p: Any) -> None:
        width = 24
        done = int(width * p.window / max(p.windows, 1))
        bar = "#" * done + "-" * (width - done)
        again = f"attempt {p.attempt} " if p.attempt > 1 else ""
        text = (
            f"[{bar}] {again}window {p.window}/{p.windows}  best loss {p.best_loss:9.3f}  "
            f"evals {p.evaluations:6d}  skipped {p.skipped}  elapsed {p.elapsed_s:5.1f}s  ETA {p.eta_s:5.1f}s"
        )
        if self._tty:
            sys.stderr.write(f"\r{text} ")
        elif (p.attempt, p.window) != self._last_window:
            sys.stderr.write(f"{text}\n")
            self._last_window = (p.attempt, p.window)
        sys.stderr.flush()

    def finish(self) -> None:
        """End the rewritten line so what follows starts on its own."""
        if self._tty:
            print(file=sys.stderr)
