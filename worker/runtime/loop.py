"""The worker loop: claim a job, run it under a heartbeat, write the outcome, take the next (issue #5.1).

This is the part of a Ray worker actor that knows nothing of Ray: ``worker.runtime.actor`` wraps it, and
tests drive it directly against a real queue. The job itself is a pluggable function, so the loop can be
tested with a cheap job and the refinement plugged in by ``worker.runtime.jobs``.

Every write goes through the queue with the claim's lease token, so a worker whose lease expired (it was
paused, partitioned, or presumed dead and its job re-run elsewhere) can never overwrite anything: the
queue raises ``LeaseLostError`` and the loop moves on (DESIGN §2: exactly-once effect on the result).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from common.errors import HoiRefineError, JobCancelledError, LeaseLostError
from common.job_options import JobOptions
from common.queue_types import ClaimedJob
from worker.runtime.backoff import Backoff, WorkerStopping, call_with_backoff, is_unreachable
from worker.runtime.heartbeat import Heartbeat
from worker.runtime.priority import lower_this_thread

log = logging.getLogger(__name__)

ProgressFn = Callable[[dict[str, Any]], None]
StopFn = Callable[[], bool]


class QueueLike(Protocol):
    """The subset of ``common.queue.JobQueue`` a worker uses."""

    def claim(self, worker_id: str, lease_seconds: float | None = None) -> ClaimedJob | None: ...
    def heartbeat(self, job_id: str, lease_token: str, progress: dict[str, Any] | None = None) -> bool: ...
    def complete(
        self, job_id: str, lease_token: str, result: bytes, summary: dict[str, Any], artifacts: Any = ()
    ) -> Any: ...
    def fail(self, job_id: str, lease_token: str, error: str, retryable: bool = False) -> Any: ...
    def acknowledge_cancel(self, job_id: str, lease_token: str) -> Any: ...
    def release(self, job_id: str, lease_token: str) -> Any: ...
    def requeue_expired(self, now: Any = None) -> int: ...


class JobFunction(Protocol):
    """Runs one job: returns (result bytes, summary); calls ``progress`` freely and ``should_stop`` once
    per unit of work (a CMA-ES generation), raising ``JobCancelledError`` when it returns True."""

    def __call__(
        self, payload: bytes, options: JobOptions, progress: ProgressFn, should_stop: StopFn
    ) -> tuple[bytes, dict[str, Any]]: ...


#: Makes the files stored beside a successful job's result (``worker.runtime.jobs.refine_preview``): takes the
#: result bytes and the job's options, returns ``common.queue_types.Artifact`` items (none when the options say so).
ArtifactFn = Callable[[bytes, JobOptions], list[Any]]

#: ``run_once(overlap=True)``'s answer for a job whose preview and result write go on in the background.
FINISHING = "finishing"


@dataclass
class CurrentJob:
    job_id: str
    lease_token: str
    attempt: int
    started: float = field(default_factory=time.monotonic)


class WorkerLoop:
    """Claims and runs jobs one at a time until ``stop()``; see the module docstring."""

    def __init__(
        self,
        queue: QueueLike,
        job_fn: JobFunction,
        worker_id: str,
        lease_seconds: float,
        idle_poll_seconds: float = 1.0,
        backoff: Backoff | None = None,
        heartbeat_interval: float | None = None,
        extra_progress: dict[str, Any] | None = None,
        artifact_fn: ArtifactFn | None = None,
        overlap_preview: bool = False,
        preview_nice: int = 0,
    ) -> None:
        if not lease_seconds > 0:
            raise ValueError(f"lease_seconds must be > 0, got {lease_seconds}")
        self.queue = queue
        self.job_fn = job_fn
        self.worker_id = worker_id
        self.lease_seconds = float(lease_seconds)
        # lease / 3: two renewals may fail before the lease runs out (DESIGN §2).
        self.heartbeat_interval = heartbeat_interval or self.lease_seconds / 3.0
        self.idle_poll_seconds = idle_poll_seconds
        self.backoff = backoff or Backoff()
        self.extra_progress = dict(extra_progress or {})
        self.artifact_fn = artifact_fn
        # ``run`` draws a job's preview beside the next job's computation (see ``run``).
        self.overlap_preview = overlap_preview
        # How much lower the thread drawing that preview runs than the computation: at the same priority it takes
        # a third of the two cores from the rollouts; lower, it mostly fills their waits at the generation barriers.
        self.preview_nice = preview_nice
        self.stop_event = threading.Event()
        self.jobs_done: dict[str, int] = {}
        self._lock = threading.Lock()
        self._current: CurrentJob | None = None
        self._last_requeue = -float("inf")
        self._heartbeat: Heartbeat | None = None
        # The previous job's preview and result write, still running while this loop computes the next job
        # (``run``): at most one at a time.
        self._finishing: threading.Thread | None = None
        self._finishing_job: str | None = None

    # ------------------------------------------------------------------ control (any thread)

    def stop(self) -> None:
        """Graceful stop: the running job (if any) stops within one generation and is released."""
        self.stop_event.set()
        with self._lock:
            if self._heartbeat is not None:
                self._heartbeat.request_stop()

    def current(self) -> CurrentJob | None:
        with self._lock:
            return self._current

    def status(self) -> dict[str, Any]:
        cur = self.current()
        with self._lock:
            finishing, done = self._finishing_job, dict(self.jobs_done)
        return {
            "worker_id": self.worker_id,
            "pid": os.getpid(),
            "job_id": cur.job_id if cur else None,
            "lease_token": cur.lease_token if cur else None,
            "finishing_job_id": finishing,
            "jobs_done": done,
        }

    # ------------------------------------------------------------------ loop

    def run(self, max_jobs: int | None = None) -> dict[str, int]:
        """Loop until ``stop()`` (or ``max_jobs`` outcomes other than idle); returns outcome counts.

        With ``overlap_preview`` a job's preview is drawn beside the next job's computation
        (``run_once(overlap=True)``): the preview runs largely on one thread, and would otherwise leave the other
        cores of a multi-threaded worker idle. The last one is waited for before this returns, so every claimed job
        has its outcome written."""
        log.info("worker %s (pid %d) started", self.worker_id, os.getpid())
        done = 0
        try:
            while not self.stop_event.is_set():
                try:
                    outcome = self.run_once(overlap=self.overlap_preview)
                except WorkerStopping:
                    break
                if outcome == "idle":
                    self.stop_event.wait(self.idle_poll_seconds)
                    continue
                done += 1
                if max_jobs is not None and done >= max_jobs:
                    break
        finally:
            self._wait_for_finishing()
        log.info("worker %s stopped after %s", self.worker_id, self.jobs_done)
        return dict(self.jobs_done)

    def _db(self, what: str, fn: Callable[[], Any]) -> Any:
        return call_with_backoff(fn, what, self.backoff, stop=self.stop_event, logger=log)

    def run_once(self, overlap: bool = False) -> str:
        """Claim and run at most one job; returns its outcome or ``"idle"``. With ``overlap`` a successful job's
        preview and result write go on in the background and this returns ``"finishing"`` (the outcome is counted
        when it is written); otherwise the outcome is written before this returns."""
        # Expired leases of dead workers go back to QUEUED before we look for work (issue #5.2).
        # At most once per heartbeat interval: an idle worker polls every second, and each requeue is a write
        # transaction (on SQLite it takes the database write lock).
        now = time.monotonic()
        if now - self._last_requeue >= self.heartbeat_interval:
            self._last_requeue = now
            requeued = self._db("requeue_expired", self.queue.requeue_expired)
            if requeued:
                log.info("requeued %d job(s) whose lease expired", requeued)
        if self.stop_event.is_set():
            return "idle"  # do not claim a job only to release it at once
        claimed = self._db("claim", lambda: self.queue.claim(self.worker_id, lease_seconds=self.lease_seconds))
        if claimed is None:
            return "idle"
        outcome = self._run_claimed(claimed, overlap)
        if outcome != FINISHING:
            self._count(outcome)
        return outcome

    def _count(self, outcome: str) -> None:
        with self._lock:
            self.jobs_done[outcome] = self.jobs_done.get(outcome, 0) + 1

    def _wait_for_finishing(self) -> None:
        thread = self._finishing
        if thread is not None:
            thread.join()
            self._finishing = None

    def _run_claimed(self, job: ClaimedJob, overlap: bool = False) -> str:
        log.info("claimed job %s (attempt %d) %r", job.job_id, job.attempt, job.name)
        base = {**self.extra_progress, "worker_id": self.worker_id, "pid": os.getpid(), "attempt": job.attempt}
        hb = Heartbeat(
            lambda progress: bool(self.queue.heartbeat(job.job_id, job.lease_token, progress)),
            interval=self.heartbeat_interval,
            lease_seconds=self.lease_seconds,
            base_progress=base,
        )
        with self._lock:
            self._current = CurrentJob(job.job_id, job.lease_token, job.attempt)
            self._heartbeat = hb
        if self.stop_event.is_set():
            hb.request_stop()
        # First beat at once: the job's progress shows which process runs it before any work is done.
        hb.beat()
        hb.start()
        outcome = ""
        try:
            outcome = self._execute(job, hb, overlap)
            return outcome
        finally:
            if outcome != FINISHING:  # else the finishing thread stops the heartbeat once the result is written
                hb.stop()
            with self._lock:
                self._current = None
                self._heartbeat = None

    def _execute(self, job: ClaimedJob, hb: Heartbeat, overlap: bool = False) -> str:
        t0 = time.monotonic()
        try:
            if hb.should_stop():
                raise JobCancelledError("stopped before start")
            result, summary = self.job_fn(job.payload, job.options, hb.update, hb.should_stop)
        except JobCancelledError:
            return self._after_stop(job, hb)
        except Exception as exc:
            if hb.lease_lost:
                log.warning("job %s errored after its lease was lost; nothing written", job.job_id)
                return "lost"
            # Input errors and project errors are deterministic: retrying cannot help. Anything else
            # (a crash in a dependency, memory) may be transient: the queue retries up to max attempts.
            retryable = not isinstance(exc, HoiRefineError)
            log.exception("job %s failed (retryable=%s)", job.job_id, retryable)
            error = _error_text(exc)
            return self._write(job, "failed", lambda: self.queue.fail(job.job_id, job.lease_token, error, retryable))
        computed = time.monotonic() - t0
        log.info("job %s computed in %.1f s", job.job_id, computed)
        # Beside ``preview.seconds``: a job's run time (claim to result) also holds its preview, and with
        # ``overlap_preview`` the previous job's preview drawn beside this one's computation.
        summary["compute_seconds"] = round(computed, 3)
        # One preview at a time: a job that finishes its computation before the previous job's preview waits here.
        self._wait_for_finishing()
        if overlap and self.artifact_fn is not None and job.options.preview_video:
            thread = threading.Thread(
                target=self._finish_in_background, args=(job, result, summary, hb), name=f"finish-{job.job_id}"
            )
            with self._lock:
                self._finishing, self._finishing_job = thread, job.job_id
            thread.start()
            return FINISHING
        return self._finish(job, result, summary, hb)

    def _finish_in_background(self, job: ClaimedJob, result: bytes, summary: dict[str, Any], hb: Heartbeat) -> None:
        lower_this_thread(self.preview_nice)
        try:
            self._count(self._finish(job, result, summary, hb))
        except Exception:
            # The lease runs out and the job is run again; the loop goes on with the next job.
            log.exception("job %s: writing its result failed", job.job_id)
            self._count("error")
        finally:
            hb.stop()
            with self._lock:
                self._finishing_job = None

    def _finish(self, job: ClaimedJob, result: bytes, summary: dict[str, Any], hb: Heartbeat) -> str:
        """The preview (when asked for) and the result, written under the job's lease."""
        artifacts = self._artifacts(job, result, summary, hb)
        if artifacts:
            return self._write(job, "succeeded", lambda: self.queue.complete(
                job.job_id, job.lease_token, result, summary, artifacts=artifacts))  # fmt: skip
        return self._write(
            job, "succeeded", lambda: self.queue.complete(job.job_id, job.lease_token, result, summary)
        )

    def _artifacts(self, job: ClaimedJob, result: bytes, summary: dict[str, Any], hb: Heartbeat) -> list[Any]:
        """The preview files of a successful job, still under its lease (the heartbeat runs). A preview that
        fails does not fail the job: the error goes into the summary's ``preview`` entry."""
        if self.artifact_fn is None or not job.options.preview_video:
            return []
        hb.update({"stage": "preview"})  # shown while the video renders
        t0 = time.monotonic()
        try:
            items = self.artifact_fn(result, job.options)
        except Exception as exc:
            log.exception("job %s: preview failed; the result is stored without it", job.job_id)
            summary["preview"] = {"error": _error_text(exc)}
            return []
        if items:
            summary["preview"] = {"files": [a.name for a in items], "seconds": round(time.monotonic() - t0, 3)}
            log.info("job %s: preview (%d files) in %.1f s", job.job_id, len(items), time.monotonic() - t0)
        return items

    def _after_stop(self, job: ClaimedJob, hb: Heartbeat) -> str:
        if hb.lease_lost:
            log.warning("job %s stopped: lease lost, nothing written", job.job_id)
            return "lost"
        if hb.cancel_requested:
            log.info("job %s cancelled", job.job_id)
            return self._write(job, "cancelled", lambda: self.queue.acknowledge_cancel(job.job_id, job.lease_token))
        log.info("job %s released (worker stopping)", job.job_id)
        return self._write(job, "released", lambda: self.queue.release(job.job_id, job.lease_token))

    def _write(self, job: ClaimedJob, outcome: str, fn: Callable[[], Any]) -> str:
        """A token-checked write; a lost lease means another attempt owns the job now."""
        next_delay = self.backoff.delays()
        while True:
            try:
                fn()
                return outcome
            except LeaseLostError as exc:
                log.warning("job %s: lease lost before writing %s (%s); nothing written", job.job_id, outcome, exc)
                return "lost"
            except Exception as exc:
                if not is_unreachable(exc):
                    raise
                delay = next_delay()
                log.warning("database unreachable writing %s of job %s; retry in %.1f s", outcome, job.job_id, delay)
                # Not interruptible by stop(): the result is worth waiting for while the lease may live.
                time.sleep(delay)


def _error_text(exc: BaseException) -> str:
    text = f"{type(exc).__name__}: {exc}"
    return text[:2000]
