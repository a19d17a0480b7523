"""Concurrency on SQLite and PostgreSQL: claimer processes never share a job; concurrent idempotent
submissions make one job."""

from __future__ import annotations

import threading
from collections import Counter

import pytest

from common.job_options import JobOptions
from common.queue import JobQueue
from common.queue_types import JobRecord
from tests.support.queue_claimer import run_claimers
from tests.support.queue_fixtures import BACKENDS, tiny_payload

pytestmark = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)

CLAIMERS = 8
JOBS = 200


@pytest.mark.slow
def test_eight_claimer_processes_claim_each_job_exactly_once(queue: JobQueue, owner: str, db_url: str) -> None:
    payload = tiny_payload()
    submitted = {queue.submit(owner, payload, JobOptions(seed=i), None, f"j{i}", 5)[0].id for i in range(JOBS)}
    per_worker, _ = run_claimers(db_url, CLAIMERS)
    claimed = [job_id for done in per_worker for job_id in done]
    assert Counter(claimed).most_common(1)[0][1] == 1, "a job was claimed twice"
    assert set(claimed) == submitted
    assert sum(1 for done in per_worker if done) >= 2, "claims did not interleave across processes"
    stats = queue.stats()
    assert stats.jobs_by_state == {"SUCCEEDED": JOBS} and stats.claims_total == JOBS
    for job_id in list(submitted)[:5]:
        blob, summary = queue.get_result(owner, job_id)
        assert blob == b"result-of-" + job_id.encode() and summary["by"].startswith("claimer-")


def test_concurrent_identical_submissions_with_one_idempotency_key_make_one_job(queue: JobQueue, owner: str) -> None:
    payload = tiny_payload(7)
    barrier = threading.Barrier(10)
    answers: list[tuple[JobRecord, bool]] = []
    failures: list[BaseException] = []

    def submit() -> None:
        barrier.wait()
        try:
            answers.append(queue.submit(owner, payload, JobOptions(seed=7), "same-key", "tiny", 5))
        except BaseException as exc:  # collected and re-raised by the assertion below
            failures.append(exc)

    threads = [threading.Thread(target=submit) for _ in range(10)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not failures, failures
    assert len({job.id for job, _ in answers}) == 1
    assert [created for _, created in answers].count(True) == 1
    assert queue.stats().jobs_by_state == {"QUEUED": 1}
