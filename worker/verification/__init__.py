"""Verification (issue #15 item 1, issue #54 item 6): recompute everything a refinement result claims and compare.

Modules:

* ``check``    ``check_result`` / ``verify_result``: the stored physics config against the product's defaults,
               then the result's inputs re-derived (``worker.refine.derive.derive_result``, the function that
               made it) and every stored array and figure compared;
* ``arrays``   the array checks: stored arrays against the fresh derivation, and against each other;
* ``summary``  the summary checks: metrics (both protocols), attempts and sequence facts;
* ``report``   ``VerifyReport`` (what ``verify`` reports) and ``Tolerances`` (what it allows on another host);
* ``folder``   ``verify_file``: one file to a ``FileVerdict`` (passed / failed / unreadable, never raising), the one
               place a file meets the checks; ``verify_files`` runs it over a process pool (``hoi-refine verify DIR``).

Science-side: nothing here imports Ray, SQLAlchemy, FastAPI or the queue. ``hoi-refine verify`` (``worker.commands``)
and the worker's check before storing a result (``worker.runtime.jobs``) both call ``check_result``.
"""

from worker.verification.check import check_result, verify_result
from worker.verification.folder import FileVerdict, find_results, verify_file, verify_files
from worker.verification.report import CROSS_HOST, Tolerances, VerifyReport

__all__ = ["CROSS_HOST", "FileVerdict", "Tolerances", "VerifyReport", "check_result", "find_results", "verify_file",
           "verify_files", "verify_result"]
