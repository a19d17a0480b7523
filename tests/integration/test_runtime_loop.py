"""The worker loop against the real queue (SQLite, and PostgreSQL when it answers), without Ray.

The job is ``worker.runtime.jobs.SelfTestJob`` (no physics), so each test takes about a second.
"""

from __future__ import annotations

import io
import logging
import os
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from common.api_key_store import ApiKeyStore
from common.database import create_engine_for
from common.job_options import JobOptions
from common.queue import JobQueue
from common.queue_types import Artifact
from common.settings import Settings
from tests.support.queue_fixtures import BACKENDS
from worker.runtime.backoff import Backoff, WorkerStopping, call_with_backoff
from worker.runtime.jobs import SELFTEST_GENERATION_ENV, SelfTestJob
from worker.runtime.loop import WorkerLoop

GEN_S = 0.1
LEASE_S = 1.5
BACKEND = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)


@pytest.fixture
def rt_queue(db_url: str, monkeypatch: pytest.MonkeyPatch) -> Iterator[JobQueue]:
    """The real queue on a migrated database (SQLite, or PostgreSQL via the shared ``db_url`` fixture)."""
    monkeypatch.setenv(SELFTEST_GENERATION_ENV, str(GEN_S))
    engine = create_engine_for(db_url)
    yield JobQueue(engine, settings=Settings(lease_seconds=LEASE_S, retry_backoff_seconds=0))
    engine.dispose()


def _submit(q: JobQueue, generations: int, name: str = "job") -> str:
    owner, _ = ApiKeyStore(q.engine).create("test")
    rec, _ = q.submit(owner, name.encode() * 10, JobOptions(seed=3, max_generations=generations), None, name, 10)
    return rec.id


def _loop(q: JobQueue, worker_id: str = "w1") -> WorkerLoop:
    return WorkerLoop(q, SelfTestJob(), worker_id=worker_id, lease_seconds=LEASE_S, idle_poll_seconds=0.05)


def _wait(pred: object, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():  # type: ignore[operator]
            return
        time.sleep(0.02)
    raise AssertionError("condition not met in time")


@BACKEND
def test_success_writes_result_and_progress_names_the_process(rt_queue: JobQueue) -> None:
    job_id = _submit(rt_queue, generations=3)
    loop = _loop(rt_queue)
    assert loop.run_once() == "succeeded"
    assert loop.run_once() == "idle"
    rec = rt_queue.get(None, job_id)
    assert rec.state == "SUCCEEDED" and rec.attempt == 1
    blob, summary = rt_queue.get_result(None, job_id)
    assert summary["generations"] == 3
    assert summary["compute_seconds"] >= 3 * GEN_S  # the job function's time (3 generations' sleeps), by the loop
    with np.load(io.BytesIO(blob)) as data:
        assert data["values"].shape == (32,)
    assert (rec.progress or {}).get("pid") == os.getpid()
    kinds = [e.kind for e in rt_queue.events(None, job_id)]
    # Heartbeats whose progress moved are logged between the claim and the result.
    assert kinds[:2] == ["submitted", "claimed"] and kinds[-1] == "succeeded" and "progress" in kinds
    assert set(kinds[2:-1]) == {"progress"}


@BACKEND
def test_progress_is_visible_while_running_and_cancel_stops_within_a_generation(rt_queue: JobQueue) -> None:
    job_id = _submit(rt_queue, generations=200)
    loop = _loop(rt_queue)
    t = threading.Thread(target=loop.run_once)
    t.start()
    _wait(lambda: (rt_queue.get(None, job_id).progress or {}).get("generation", 0) >= 2, 10)
    progress = rt_queue.get(None, job_id).progress or {}
    assert progress["pid"] == os.getpid() and progress["worker_id"] == "w1" and progress["attempt"] == 1
    rt_queue.cancel(None, job_id)
    t.join(30)  # a generous bound on a hung loop, not a speed check: the work is counted below
    assert not t.is_alive()
    assert rt_queue.get(None, job_id).state == "CANCELLED"
    # It stopped long before its 200 generations: the last progress it reported is far from the end.
    last = (rt_queue.get(None, job_id).progress or {}).get("generation", 0)
    assert last < 200 // 2, last
    assert loop.jobs_done == {"cancelled": 1}


@BACKEND
def test_graceful_stop_releases_the_job_without_consuming_an_attempt(rt_queue: JobQueue) -> None:
    job_id = _submit(rt_queue, generations=200)
    loop = _loop(rt_queue)
    t = threading.Thread(target=loop.run)
    t.start()
    _wait(lambda: rt_queue.get(None, job_id).state == "RUNNING", 10)
    loop.stop()
    t.join(5)
    assert not t.is_alive()
    rec = rt_queue.get(None, job_id)
    assert rec.state == "QUEUED" and rec.attempt == 1
    assert loop.jobs_done == {"released": 1}


@BACKEND
def test_run_draws_a_jobs_preview_while_the_next_job_computes_and_writes_every_outcome(rt_queue: JobQueue) -> None:
    owner, _ = ApiKeyStore(rt_queue.engine).create("test")
    first, _ = rt_queue.submit(owner, b"first" * 10, JobOptions(seed=1, max_generations=2), None, "first", 10)
    second, _ = rt_queue.submit(owner, b"second" * 10, JobOptions(seed=2, max_generations=4), None, "second", 10)
    seen: dict[int, str] = {}
    nice: list[int] = []

    def preview(result: bytes, options: JobOptions) -> list[Artifact]:
        nice.append(os.getpriority(os.PRIO_PROCESS, 0))  # this thread's (Linux keeps nice per thread)
        if options.seed == 1:
            # Held until the second job is being computed: a loop that drew previews between jobs never gets there
            # (and the preview's error would be stored instead of its file).
            _wait(lambda: (rt_queue.get(None, second.id).progress or {}).get("generation", 0) >= 1, 10)
            seen[1] = rt_queue.get(None, second.id).state
        return [Artifact("video.mp4", "video/mp4", b"mp4:" + result[:4], 8)]

    loop = WorkerLoop(rt_queue, SelfTestJob(), worker_id="w1", lease_seconds=LEASE_S, idle_poll_seconds=0.05,
                      artifact_fn=preview, overlap_preview=True, preview_nice=3)  # fmt: skip
    base = os.getpriority(os.PRIO_PROCESS, 0)
    assert loop.run(max_jobs=2) == {"succeeded": 2}  # returns once the last preview is written, not before
    assert seen == {1: "RUNNING"}
    # The previews ran on their own threads, below the computation's priority; this thread kept its own.
    assert nice == [min(base + 3, 19)] * 2 and os.getpriority(os.PRIO_PROCESS, 0) == base
    for job in (first, second):
        rec = rt_queue.get(None, job.id)
        assert rec.state == "SUCCEEDED" and rec.summary["preview"]["files"] == ["video.mp4"]  # type: ignore[index]
        assert rt_queue.get_artifact(owner, job.id, "video.mp4").data.startswith(b"mp4:")
    # The first job's result was written (under its own lease, its heartbeat beating) after the second was claimed.
    first_done = rt_queue.get(None, first.id).finished_at
    second_started = rt_queue.get(None, second.id).started_at
    assert first_done is not None and second_started is not None and first_done > second_started
    assert loop.status()["finishing_job_id"] is None and loop.current() is None


@BACKEND
def test_worker_that_lost_its_lease_writes_nothing_and_the_next_attempt_wins(rt_queue: JobQueue) -> None:
    job_id = _submit(rt_queue, generations=30)
    # A stalled worker: it beats once at claim time and then never again (interval far beyond the lease).
    first = WorkerLoop(rt_queue, SelfTestJob(), "stalled", lease_seconds=LEASE_S, heartbeat_interval=600)
    t = threading.Thread(target=first.run_once)
    t.start()
    _wait(lambda: rt_queue.get(None, job_id).state == "RUNNING", 10)
    time.sleep(LEASE_S + 0.2)
    second = _loop(rt_queue, "fresh")
    assert second.run_once() == "succeeded"  # requeues the expired job itself, then claims it
    t.join(10)
    # The stalled worker finished its computation later; its token-checked write changed nothing.
    assert first.jobs_done == {"lost": 1}
    rec = rt_queue.get(None, job_id)
    assert rec.state == "SUCCEEDED" and rec.attempt == 2
    kinds = [e.kind for e in rt_queue.events(None, job_id)]
    assert kinds.count("succeeded") == 1 and kinds.count("requeued") == 1 and kinds.count("claimed") == 2


def test_unreachable_database_is_retried_with_backoff_and_logged(caplog: pytest.LogCaptureFixture) -> None:
    engine = create_engine_for("postgresql+psycopg://postgres@127.0.0.1:1/none?connect_timeout=1")
    q = JobQueue(engine)
    stop = threading.Event()
    threading.Timer(1.2, stop.set).start()
    with caplog.at_level(logging.WARNING), pytest.raises(WorkerStopping):
        call_with_backoff(lambda: q.claim("w"), "claim", Backoff(first=0.2, maximum=0.4), stop=stop)
    lines = [r.getMessage() for r in caplog.records if "database unreachable during claim" in r.getMessage()]
    assert len(lines) >= 2
    assert "retry 1 in 0.2 s" in lines[0] and "retry 2 in 0.4 s" in lines[1]


def test_loop_keeps_retrying_an_unreachable_database_until_stopped(caplog: pytest.LogCaptureFixture) -> None:
    engine = create_engine_for("postgresql+psycopg://postgres@127.0.0.1:1/none?connect_timeout=1")
    loop = WorkerLoop(JobQueue(engine), SelfTestJob(), "w", lease_seconds=3, backoff=Backoff(0.1, 0.2))
    t = threading.Thread(target=loop.run)
    with caplog.at_level(logging.WARNING):
        t.start()
        time.sleep(1.0)
        loop.stop()
        t.join(5)
    assert not t.is_alive()
    assert sum("database unreachable" in r.getMessage() for r in caplog.records) >= 2
