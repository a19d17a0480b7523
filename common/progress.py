"""A running job's progress document (``jobs.progress``, the API's ``progress``; issue #53 item 4).

The worker sends it with every lease renewal; the API, the dashboard, ``submit`` and the demo read it. Keys
(all optional: a job that has not started its computation has only the first three):

* ``worker_id``, ``pid``: the process running the job;
* ``attempt``: the *queue's* attempt at the job (the job's ``attempt``: 2 after a lost lease or a retry);
* ``fraction``: 0..1 over the whole job (every refinement attempt, polish sweep and rescue, the result's
  derivation, its verification and the preview); it only goes forward, also when the plan grows (a further
  attempt, a rescue): the rest of the bar then fills more slowly;
* ``stage``: what runs now, for people: ``"preparing"``, ``"attempt 2 of 4"``, ``"polish sweep 3"``,
  ``"compiling finer parts for a rescue"`` (the rescue's convex decomposition and scene: seconds to minutes, the
  fraction holds still), ``"rescue on finer parts: attempt 1 of 4"``, ``"rescue on finer parts: polish sweep 2"``,
  ``"deriving the result"``, ``"verifying"``, ``"preview"``, ``"done"``;
* ``step``: the same for programs, one of ``STEPS``;
* ``eta_s``: seconds until the whole job is done (estimated from this job's own pace; null before any pace is
  known; 0 when done);
* ``elapsed_s``: seconds since the worker started the job's computation;
* ``refine_attempt`` / ``refine_attempts``: the refinement's own attempt (1-based: the first run of the window
  loop, then its restarts) and the most the job's options allow; on a rescue they count the rescue's attempts;
* ``polish_sweep``: the polish sweep running (1-based), else absent;
* ``window`` / ``windows``: the sliding window within the current attempt or sweep; ``best_loss`` its best loss
  so far; ``evaluations``: candidate evaluations in the job so far; ``skipped``: windows skipped in this pass.

A SUCCEEDED job's document is ``finished_progress`` of the last one: ``fraction`` 1, ``stage``/``step`` "done",
``eta_s`` 0, the window fields dropped. Before issue #53 ``attempt`` meant the refinement's restart once the
refinement reported (now ``refine_attempt``), ``eta_s`` was the current pass's and a finished job kept its last
window and ETA.
"""

from __future__ import annotations

from typing import Any, Literal

Step = Literal["prepare", "attempt", "polish", "rescue_compile", "rescue", "derive", "verify", "preview", "done"]
STEPS: tuple[str, ...] = Step.__args__  # type: ignore[attr-defined]
#: The ``stage`` texts of the steps that have a single one.
STAGE_TEXT: dict[str, str] = {"prepare": "preparing", "rescue_compile": "compiling finer parts for a rescue",
                              "derive": "deriving the result", "verify": "verifying", "preview": "preview",
                              "done": "done"}
#: Keys that describe the pass running now, dropped once the job is done.
PASS_KEYS: tuple[str, ...] = ("window", "windows", "best_loss", "skipped", "refine_attempt", "refine_attempts",
                              "polish_sweep", "generation")


def finished_progress(previous: dict[str, Any] | None) -> dict[str, Any]:
    """The progress document of a job that finished successfully, from its last one (``common.queue``)."""
    kept = {k: v for k, v in (previous or {}).items() if k not in PASS_KEYS}
    return {**kept, "fraction": 1.0, "stage": STAGE_TEXT["done"], "step": "done", "eta_s": 0.0}
