"""The whole job's progress over a real run with restarts and a rescue (issue #53 item 4): the worker's refinement
job (``RefineJob``: refinement, derivation, verification, with the preview announced) reports through the lease
heartbeat one document whose fraction only goes forward, whose stages come in the plan's order, and whose queue
attempt is not the refinement's."""

from __future__ import annotations

from typing import Any

from common.progress import STEPS, finished_progress
from common.sequence_io import sequence_to_npz_bytes
from tests.integration.test_refine_rescue import QUICK, _ring_push
from worker.runtime.heartbeat import Heartbeat
from worker.runtime.jobs import RefineJob


def test_progress_goes_forward_over_restarts_and_a_rescue_and_ends_done() -> None:
    hb = Heartbeat(lambda progress: False, interval=60.0, base_progress={"worker_id": "w1", "attempt": 1})
    sent: list[dict[str, Any]] = []

    def progress(doc: dict[str, Any]) -> None:
        hb.update(doc)
        sent.append(hb.progress())

    # No hand motion lifts the ring 20 cm: both attempts fail, then both of the rescue's (test_refine_rescue).
    options = QUICK.model_copy(update={"preview_video": True})
    _blob, summary = RefineJob(2)(sequence_to_npz_bytes(_ring_push(0.2)), options, progress, lambda: False)
    assert [a["convex_detail"] for a in summary["attempts"]] == ["coarse", "coarse", "fine", "fine"]

    fractions = [d["fraction"] for d in sent]
    assert fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] < 1.0
    stages = list(dict.fromkeys(d["stage"] for d in sent))
    assert stages == ["preparing", "attempt 1 of 2", "attempt 2 of 2", "rescue on finer parts: attempt 1 of 2",
                      "rescue on finer parts: attempt 2 of 2", "deriving the result", "verifying", "preview"]
    assert list(dict.fromkeys(d["step"] for d in sent)) == [s for s in STEPS if s not in ("polish", "done")]
    # The queue's attempt stays the job's; the refinement's own is another key.
    assert all(d["attempt"] == 1 for d in sent)
    assert [d["refine_attempt"] for d in sent if "refine_attempt" in d][-1] == 2
    assert all(d["refine_attempts"] == 2 for d in sent if "refine_attempt" in d)
    # The evaluations count over the whole job; the ETA is known once the first pass has a pace.
    assert sent[-1]["evaluations"] == summary["timings"]["evaluations"]
    assert all(d["eta_s"] is None or d["eta_s"] >= 0 for d in sent)
    assert sent[-1]["eta_s"] is not None
    done = finished_progress(sent[-1])
    assert (done["fraction"], done["stage"], done["eta_s"], done["attempt"]) == (1.0, "done", 0.0, 1)
    assert "window" not in done and "refine_attempt" not in done


def test_reporting_progress_leaves_the_result_unchanged() -> None:
    from tests.support.synthetic_push import push_sequence
    from worker.refine.job_progress import JobProgress
    from worker.refine.run import refine_sequence

    seq = push_sequence(30)
    options = QUICK.model_copy(update={"polish": True})
    tracker = JobProgress(options.restarts, options.polish)
    docs: list[dict[str, Any]] = []
    reported = refine_sequence(seq, options, progress=lambda p: docs.append(tracker.window(p)))
    silent = refine_sequence(seq, options)
    assert reported.to_npz_bytes(wall_clock=False) == silent.to_npz_bytes(wall_clock=False)
    assert docs[-1]["step"] == "derive" and len({d["stage"] for d in docs}) >= 2
