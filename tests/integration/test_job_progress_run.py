"""The whole job's progress over a real run with restarts and a rescue (issue #53 item 4): a worker loop on the real
queue (SQLite) runs the refinement job (``RefineJob``: refinement, derivation, verification, then the loop's preview);
the job reports one document whose fraction only goes forward and whose stages come in the plan's order, the queue
stores it with the queue's attempt beside the refinement's, and the finished job shows done."""

from __future__ import annotations

from typing import Any

from common.api_key_store import ApiKeyStore
from common.database import create_engine_for
from common.job_options import JobOptions
from common.progress import STEPS
from common.queue import JobQueue
from common.sequence_io import sequence_to_npz_bytes
from common.settings import Settings
from tests.integration.test_refine_rescue import QUICK, _ring_push
from worker.runtime.jobs import RefineJob, make_artifact_function
from worker.runtime.loop import WorkerLoop

#: Renewals every second (a third of the lease), so the queue stores the progress many times over the run.
LEASE_S = 3.0


class RecordingRefineJob(RefineJob):
    """The worker's refinement job, keeping every progress document it sends to the heartbeat."""

    def __init__(self, threads: int) -> None:
        super().__init__(threads)
        self.sent: list[dict[str, Any]] = []

    def __call__(self, payload: bytes, options: JobOptions, progress: Any, should_stop: Any) -> Any:
        def forward(doc: dict[str, Any]) -> None:
            self.sent.append(doc)
            progress(doc)

        return super().__call__(payload, options, forward, should_stop)


def test_progress_goes_forward_over_restarts_and_a_rescue_and_ends_done(db_url: str) -> None:
    engine = create_engine_for(db_url)
    queue = JobQueue(engine, settings=Settings(lease_seconds=LEASE_S, retry_backoff_seconds=0))
    owner, _ = ApiKeyStore(engine).create("test")
    # No hand motion lifts the ring 20 cm: both attempts fail, then both of the rescue's (test_refine_rescue).
    options = QUICK.model_copy(update={"preview_video": True})
    job, _ = queue.submit(owner, sequence_to_npz_bytes(_ring_push(0.2)), options, None, "ring", 30)
    job_fn = RecordingRefineJob(2)
    loop = WorkerLoop(queue, job_fn, worker_id="w1", lease_seconds=LEASE_S, idle_poll_seconds=0.05,
                      artifact_fn=make_artifact_function("refine"))  # fmt: skip
    assert loop.run_once() == "succeeded"
    _blob, summary = queue.get_result(None, job.id)
    assert [a["convex_detail"] for a in summary["attempts"]] == ["coarse", "coarse", "fine", "fine"]

    # What the job sent: a fraction that only goes forward, the stages in the plan's order.
    sent = job_fn.sent
    fractions = [d["fraction"] for d in sent]
    assert fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] < 1.0
    stages = list(dict.fromkeys(d["stage"] for d in sent))
    assert stages == ["preparing", "attempt 1 of 2", "attempt 2 of 2", "compiling finer parts for a rescue",
                      "rescue on finer parts: attempt 1 of 2", "rescue on finer parts: attempt 2 of 2",
                      "deriving the result", "verifying", "preview"]  # fmt: skip
    assert list(dict.fromkeys(d["step"] for d in sent)) == [s for s in STEPS if s not in ("polish", "done")]
    assert [d["refine_attempt"] for d in sent if "refine_attempt" in d][-1] == 2
    assert all(d["refine_attempts"] == 2 for d in sent if "refine_attempt" in d)
    assert all("attempt" not in d for d in sent)  # the queue's key is the loop's to set
    # The evaluations count over the whole job; the ETA is known once the first pass has a pace.
    assert sent[-1]["evaluations"] == summary["timings"]["evaluations"]
    assert all(d["eta_s"] is None or d["eta_s"] >= 0 for d in sent) and sent[-1]["eta_s"] is not None

    # What the queue stored at the lease renewals: forward only, the queue's attempt beside the refinement's.
    stored = [e.detail["progress"] for e in queue.events(None, job.id) if e.kind == "progress"]
    assert len(stored) >= 3
    stored_fractions = [p["fraction"] for p in stored if "fraction" in p]
    assert stored_fractions == sorted(stored_fractions)
    assert all(p["attempt"] == 1 and p["worker_id"] == "w1" for p in stored)
    assert any("refine_attempt" in p for p in stored)
    # A finished job shows done.
    done = queue.get(None, job.id).progress or {}
    assert (done["fraction"], done["stage"], done["step"], done["eta_s"], done["attempt"]) == (1.0, "done", "done",
                                                                                              0.0, 1)  # fmt: skip
    assert not {"window", "windows", "refine_attempt", "polish_sweep", "best_loss"} & set(done)
    engine.dispose()


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
