"""The refinement's progress line on stderr, shared by ``refine`` and the in-process ``demo``."""

from __future__ import annotations

import sys
from typing import Any


def progress_text(doc: dict[str, Any], width: int = 24) -> str:
    """One line of a whole-job progress document (``common.progress``): the bar over the whole job, the stage,
    the window within the pass, the best loss, the evaluations, the elapsed time and the ETA of the whole job."""
    fraction = float(doc.get("fraction") or 0.0)
    done = int(width * fraction)
    text = f"[{'#' * done}{'-' * (width - done)}] {100 * fraction:3.0f}%  {doc.get('stage', '')}"
    if doc.get("windows"):
        text += f"  window {doc['window']}/{doc['windows']}  best loss {doc['best_loss']:9.3f}"
    eta = doc.get("eta_s")
    return (text + f"  evals {doc.get('evaluations', 0):6d}  elapsed {doc.get('elapsed_s', 0.0):5.1f}s  "
            f"ETA {'?' if eta is None else f'{eta:.0f}s'}")


class ProgressBar:
    """The whole refinement's bar (``JobProgress``: every attempt, polish sweep and rescue, then the result's
    derivation), its stage, the window, best loss, evaluations and ETA: one rewritten line on a terminal; in a log
    (not a TTY), one line per finished window and stage instead of hundreds of carriage-return updates."""

    def __init__(self, restarts: int, polish: bool = True) -> None:
        from worker.refine.job_progress import JobProgress  # the refinement's modules: not for ``--help``

        self._tty = sys.stderr.isatty()
        self._tracker = JobProgress(restarts, polish)
        self._last: tuple[Any, ...] = ()

    def __call__(self, p: Any) -> None:
        doc = self._tracker.window(p)
        text = progress_text(doc)
        if self._tty:
            sys.stderr.write(f"\r{text} ")
        elif (doc["stage"], doc.get("window")) != self._last:
            sys.stderr.write(f"{text}\n")
            self._last = (doc["stage"], doc.get("window"))
        sys.stderr.flush()

    def finish(self) -> None:
        """The finished job's line (``done``), on its own line."""
        text = progress_text(self._tracker.finished())
        sys.stderr.write(f"\r{text} \n" if self._tty else f"{text}\n")
        sys.stderr.flush()
