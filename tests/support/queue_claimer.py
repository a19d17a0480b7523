"""Body of a claimer *process* for the concurrency test and ``bench/api_load.py``.

Kept apart from the fixtures so a spawned interpreter imports only the queue (not pytest, NumPy, trimesh):
eight of them start in a few seconds on two cores.
"""

from __future__ import annotations

import time
from typing import Any


def claim_until_empty(url: str, worker_id: str, barrier: Any, out: Any) -> None:
    """Wait at ``barrier`` with the other claimers, then claim + complete until the queue is empty.

    Puts ``(worker_id, [job ids], seconds spent claiming)`` on ``out``.
    """
    from common.database import create_engine_for
    from common.queue import JobQueue
    from common.settings import Settings

    engine = create_engine_for(url)
    queue = JobQueue(engine, Settings(lease_seconds=60.0))
    done: list[str] = []
    barrier.wait()
    t0 = time.perf_counter()
    try:
        while (job := queue.claim(worker_id)) is not None:
            queue.complete(job.job_id, job.lease_token, b"result-of-" + job.job_id.encode(), {"by": worker_id})
            done.append(job.job_id)
    finally:
        engine.dispose()
        out.put((worker_id, done, time.perf_counter() - t0))


def run_claimers(url: str, count: int, timeout_s: float = 120.0) -> tuple[list[list[str]], float]:
    """Start ``count`` spawned claimer processes together; returns (job ids per claimer, wall seconds)."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")  # fresh interpreters: no engine state crosses a fork
    barrier = ctx.Barrier(count)
    out = ctx.Queue()
    procs = [ctx.Process(target=claim_until_empty, args=(url, f"claimer-{i}", barrier, out)) for i in range(count)]
    for p in procs:
        p.start()
    answers = [out.get(timeout=timeout_s) for _ in procs]
    for p in procs:
        p.join(timeout=10)
    return [done for _, done, _ in answers], max(seconds for _, _, seconds in answers)
