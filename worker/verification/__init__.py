"""Verification (issue #15 item 1, issue #54 item 6): recompute everything a refinement result claims and compare.

Modules:

* ``check``    ``check_result`` / ``verify_result``: the stored physics config against the product's defaults,
               then the result's inputs re-derived (``worker.refine.derive.derive_result``, the function that
               made it) and every stored array and figure compared;
* ``arrays``   the array checks: stored arrays against the fresh derivation, and against each other;
* ``summary``  the summary checks: metrics (both protocols), attempts and sequence facts;
* ``stepwise`` ``replay_stepwise``: each stored frame's integration state against the state one frame's steps reach
               from the stored frame before it (issue #54), and the records made at the stored states;
* ``report``   ``VerifyReport`` (what ``verify`` reports) and ``Tolerances`` (what it allows on another host:
               ``CROSS_HOST`` for a whole re-simulation, ``STEPWISE`` against records made at stored states);
* ``folder``   ``verify_file``: one file to a ``FileVerdict`` (passed / failed / unreadable, never raising), the one
               place a file meets the checks; ``verify_files`` runs it over a process pool (``hoi-refine verify DIR``).

``check_result(blob) -> VerifyReport`` is the one entry point for a whole result: ``report.verified``,
``report.method`` ("stepwise", or "rollout" for an older result without states), ``report.stepwise`` per replay
(largest deviation per state field with frame and degree of freedom), ``report.failures``; ``to_dict()`` is its
JSON form.

Science-side: nothing here imports Ray, SQLAlchemy, FastAPI or the queue. ``hoi-refine verify`` (``worker.commands``)
and the worker's check before storing a result (``worker.runtime.jobs``) both call ``check_result``.
"""

from worker.verification.check import check_result, verify_result
from worker.verification.folder import FileVerdict, find_results, verify_file, verify_files
from worker.verification.report import CROSS_HOST, STEPWISE, Tolerances, VerifyReport
from worker.verification.stepwise import STATE_TOLERANCES, StateTolerances, StepwiseReport, replay_stepwise

__all__ = ["CROSS_HOST", "STATE_TOLERANCES", "STEPWISE", "FileVerdict", "StateTolerances", "StepwiseReport",
           "Tolerances", "VerifyReport", "check_result", "find_results", "replay_stepwise", "verify_file",
           "verify_files", "verify_result"]
