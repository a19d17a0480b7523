"""The whole job's progress document (``common.progress``) from the refinement's window reports (issue #53 item 4).

The window loop reports its pass (``windowed.RefineProgress``); ``run.refine_sequence`` tags each report with the
refinement's attempt, polish sweep and whether it is the rescue, and reports the result's derivation. ``JobProgress``
turns those reports into one fraction over the whole job's plan: the passes of the window loop started so far, a
reserve for the passes that may still follow (as many as started, at most as many as the options still allow:
a job that needed several passes often needs more), then the derivation, the verification and the preview,
each weighted in passes (``TAIL_PASSES``). Between the passes the rescue compiles its finer convex parts (CoACD:
seconds with a cache, minutes without): that step has a stage of its own and no share of the bar, which holds
still until the rescue's first pass, and its seconds are left out of the job's pace. The fraction only goes
forward: when the plan changes (a pass starts, the derivation ends the passes), the bar keeps its place and spreads
its rest over what the plan has left, so it fills more slowly after a further attempt and faster once the passes
are over. The ETA is that plan's remaining passes at this job's own pace (seconds per pass so far), plus the steps
after them: the verification repeats the derivation, so once the derivation ran, its time stands for the
verification's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from common.progress import STAGE_TEXT, finished_progress
from worker.refine.run import POLISH_SWEEPS
from worker.refine.windowed import RefineProgress

#: The steps after the window passes, in passes of the window loop: their share of the bar and, until the job has
#: measured its own, of the ETA. Measured on DexYCB jobs (bench/results/speed_experiments.md): a pass takes tens
#: of seconds, the derivation and the worker's verification well under one each, the preview 2-3 s.
TAIL_PASSES: dict[str, float] = {"derive": 0.05, "verify": 0.05, "preview": 0.15}
#: What the close-up video (``JobOptions.preview_close_up``) adds to the preview's weight: two thirds of the preview
#: again (bench/results/video_framing.md: 8.3 -> 13.8 s at 640x480).
CLOSE_UP_PASSES = 0.1
#: No ETA until this much of a pass and this many seconds have run: the first generations' pace says little, and
#: the first windows are often skipped in milliseconds (no hand near the object yet).
MIN_PACE_PASSES = 0.02
MIN_PACE_SECONDS = 1.0
#: The reserve for passes that may follow, per pass started (capped by what the options still allow): a job that
#: needed n passes is expected to need as many again. A smaller reserve fills the bar faster at first and then
#: squeezes a long job's later passes into its last few percent (each pass the plan did not expect takes a share
#: of what is left); with one, what is left after n passes shrinks like 1 / n.
RESERVE_PER_PASS = 1.0


class JobProgress:
    """The progress of one job refined with ``restarts`` and ``polish`` (``JobOptions``); ``verify`` / ``preview``:
    whether the job verifies its result and draws a preview after the refinement (the worker's job does both;
    ``hoi-refine refine`` neither); ``close_up``: the preview draws the close-up video too."""

    def __init__(self, restarts: int, polish: bool = True, *, verify: bool = False, preview: bool = False,
                 close_up: bool = False, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._t0 = clock()
        self._attempts = restarts + 1
        self._polish = polish
        self._passes_started = 0
        self._tail = ["derive", *(["verify"] if verify else []), *(["preview"] if preview else [])]
        self._weights = {**TAIL_PASSES, "preview": TAIL_PASSES["preview"] + (CLOSE_UP_PASSES if close_up else 0.0)}
        self._passes_done = 0.0  # finished passes of the window loop
        self._pass: tuple[bool, int, int] | None = None  # (rescue, attempt, polish sweep) of the running pass
        self._pass_fraction = 0.0
        self._pass_evaluations = 0  # of the running pass
        self._earlier_evaluations = 0  # of the finished ones
        self._passes_started_at: float | None = None
        self._passes_ended_at: float | None = None
        self._compile_s = 0.0  # seconds the rescue's compilation took (not part of the passes' pace)
        self._step = "prepare"
        self._tail_done = 0.0  # passes' worth of the tail's finished steps
        self._step_started_at = self._t0
        self._derive_s: float | None = None
        self._planned = 1.0 + self._tail_units()  # the first attempt, then the tail (until a pass reports)
        self._anchor = (0.0, 0.0)  # (fraction, work done) where the plan last changed
        self._fraction = 0.0
        self._last: dict[str, Any] = {}

    # ------------------------------------------------------------------ reports in

    def preparing(self) -> dict[str, Any]:
        """The document before the refinement's first report (the scene is being built)."""
        return self._document({})

    def window(self, p: RefineProgress) -> dict[str, Any]:
        """The document after a report of the refinement (``refine_sequence``'s ``progress``)."""
        if p.deriving:
            return self.stage("derive")
        if p.compiling_rescue:
            return self._compiling_rescue()
        key = (p.rescue, p.attempt, p.polish_sweep)
        if key != self._pass:
            if self._pass is not None:  # the previous pass ended: it counts whole
                self._end_pass()
            elif self._passes_started_at is None:
                self._passes_started_at = self._clock()
            if self._step == "rescue_compile":
                self._compile_s += self._clock() - self._step_started_at
            self._pass, self._pass_fraction, self._pass_evaluations = key, 0.0, 0
            self._passes_started += 1
            self._step = "rescue" if p.rescue else "polish" if p.polish_sweep else "attempt"
            reserve = min(RESERVE_PER_PASS * self._passes_started, self._passes_possible(p))
            self._replan(self._passes_started + reserve)
        self._pass_fraction = max(self._pass_fraction, min(max(p.fraction, 0.0), 1.0))
        self._pass_evaluations = p.evaluations
        fields = {"refine_attempt": p.attempt, "refine_attempts": p.attempts, "window": p.window,
                  "windows": p.windows, "best_loss": p.best_loss, "skipped": p.skipped}
        if p.polish_sweep:
            fields["polish_sweep"] = p.polish_sweep
        return self._document(fields)

    def stage(self, step: str) -> dict[str, Any]:
        """The document when ``step`` (``derive``, ``verify`` or ``preview``) starts; the steps before it are done."""
        if step not in self._tail:
            raise ValueError(f"{step!r} is not a step of this job's plan ({', '.join(self._tail)})")
        now = self._clock()
        if self._passes_ended_at is None:
            self._passes_ended_at = now
        if self._pass is not None:  # the window passes are over
            self._end_pass()
            self._replan(self._passes_done)  # no further pass: the reserve is dropped
        if self._step == "derive":
            self._derive_s = now - self._step_started_at
        order = self._tail.index(step)
        self._tail_done = sum(self._weights[s] for s in self._tail[:order])
        self._step, self._step_started_at = step, now
        return self._document({})

    def _compiling_rescue(self) -> dict[str, Any]:
        """The document while the rescue's finer parts compile: the pass before it ended; the plan keeps its reserve
        (it counted the rescue's passes) until the rescue's first pass replans it."""
        if self._pass is not None:
            self._end_pass()
        if self._step != "rescue_compile":  # a repeated report does not restart its clock
            self._step, self._step_started_at = "rescue_compile", self._clock()
        return self._document({})

    def _end_pass(self) -> None:
        """The running pass ended: it counts whole."""
        self._passes_done += 1.0
        self._earlier_evaluations += self._pass_evaluations
        self._pass, self._pass_fraction, self._pass_evaluations = None, 0.0, 0

    def finished(self) -> dict[str, Any]:
        """The document of the finished job (``common.progress.finished_progress``)."""
        return finished_progress(self._last)

    # ------------------------------------------------------------------ the plan and the document

    def _tail_units(self) -> float:
        return sum(self._weights[s] for s in self._tail)

    def _done(self) -> float:
        """Work done, in passes: the finished passes, the running one's share and the tail's finished steps."""
        return self._passes_done + self._pass_fraction + self._tail_done

    def _passes_possible(self, p: RefineProgress) -> float:
        """How many more passes the options allow after ``p``'s: further attempts, polish sweeps and the rescue's
        plan (which runs only after every attempt failed, so at most once and only when restarts are allowed)."""
        attempts = 0 if p.polish_sweep else p.attempts - p.attempt
        sweeps = (POLISH_SWEEPS - p.polish_sweep) if self._polish else 0
        rescue = 0 if p.rescue or p.attempts < 2 else p.attempts + (POLISH_SWEEPS if self._polish else 0)
        return float(attempts + sweeps + rescue)

    def _replan(self, passes: float) -> None:
        """The plan now has ``passes`` passes before its tail: the bar keeps its place and spreads its rest over
        what the plan has left."""
        planned = passes + self._tail_units()
        if planned != self._planned:
            self._anchor = (self._fraction, self._done())
            self._planned = planned

    def _current_fraction(self) -> float:
        start, done_at = self._anchor
        left = self._planned - done_at
        share = (self._done() - done_at) / left if left > 0 else 1.0
        return min(max(self._fraction, start + (1.0 - start) * min(max(share, 0.0), 1.0)), 1.0)

    def _eta(self, now: float) -> float | None:
        if self._passes_started_at is None:
            return None
        in_passes = self._passes_done + self._pass_fraction
        if self._step in ("attempt", "polish", "rescue_compile", "rescue"):
            # While the rescue compiles, the passes still to come and the tail (the compilation's own rest is
            # unknown: CoACD reports nothing until it ends).
            passes_s = now - self._passes_started_at - self._compiling_s(now)
            if in_passes < MIN_PACE_PASSES or passes_s < MIN_PACE_SECONDS:
                return None
            pace = passes_s / in_passes
            remaining_passes = max(self._planned - self._tail_units() - in_passes, 0.0)
            return remaining_passes * pace + sum(self._tail_seconds(s, pace) for s in self._tail)
        pace = self._pace_of_passes()
        order = self._tail.index(self._step)
        running = max(self._tail_seconds(self._step, pace) - (now - self._step_started_at), 0.0)
        return running + sum(self._tail_seconds(s, pace) for s in self._tail[order + 1:])

    def _pace_of_passes(self) -> float:
        """Seconds per pass over the job's passes (they ended when the derivation started)."""
        start = self._passes_started_at if self._passes_started_at is not None else self._t0
        end = self._passes_ended_at if self._passes_ended_at is not None else self._clock()
        return max(end - start - self._compile_s, 0.0) / max(self._passes_done, 1.0)

    def _compiling_s(self, now: float) -> float:
        """Seconds the rescue's compilation took so far (also while it runs)."""
        running = now - self._step_started_at if self._step == "rescue_compile" else 0.0
        return self._compile_s + running

    def _tail_seconds(self, step: str, pace: float) -> float:
        if step in ("derive", "verify") and self._derive_s is not None:
            return self._derive_s  # the verification repeats the derivation
        return self._weights[step] * pace

    def _document(self, fields: dict[str, Any]) -> dict[str, Any]:
        now = self._clock()
        self._fraction = self._current_fraction()
        eta = self._eta(now)
        doc: dict[str, Any] = {
            "fraction": round(self._fraction, 4),
            "stage": self._stage_text(fields),
            "step": self._step,
            "eta_s": None if eta is None or not math.isfinite(eta) else round(eta, 1),
            "elapsed_s": round(now - self._t0, 1),
            "evaluations": self._earlier_evaluations + self._pass_evaluations,
            **fields,
        }
        self._last = doc
        return doc

    def _stage_text(self, fields: dict[str, Any]) -> str:
        if self._step not in ("attempt", "polish", "rescue"):
            return STAGE_TEXT[self._step]
        sweep = fields.get("polish_sweep")
        text = f"polish sweep {sweep}" if sweep else f"attempt {fields['refine_attempt']} of {self._attempts}"
        return f"rescue on finer parts: {text}" if self._step == "rescue" else text
