"""Queue semantics (DESIGN §2) on SQLite and PostgreSQL: leases, token checks, cancel, retry, backoff."""

from __future__ import annotations

from datetime import timedelta

import pytest
import sqlalchemy as sa

from common.api_key_store import ApiKeyStore
from common.db_models import utcnow
from common.errors import (
    AuthenticationError,
    ConflictError,
    IdempotencyMismatchError,
    InvalidRequestError,
    LeaseLostError,
    LimitExceededError,
    NotFoundError,
)
from common.job_options import JobOptions
from common.queue import JobQueue, jobs, legacy_payload_hash, payload_hash
from tests.support.queue_fixtures import BACKENDS, fake_result, submit_tiny, tiny_payload

pytestmark = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)


def test_submit_claim_heartbeat_complete_round_trip(queue: JobQueue, owner: str) -> None:
    job_id = submit_tiny(queue, owner, seed=3)
    claimed = queue.claim("w1")
    assert claimed is not None and claimed.job_id == job_id and claimed.attempt == 1
    assert claimed.payload == tiny_payload(3) and claimed.options.seed == 3
    progress = {"window": 2, "windows": 7, "best_loss": 0.5, "evaluations": 40, "eta_s": 12.0}
    assert queue.heartbeat(job_id, claimed.lease_token, progress) is False
    assert queue.get(owner, job_id).progress == progress
    # A renewal with the same progress logs no second "progress" event.
    assert queue.heartbeat(job_id, claimed.lease_token, progress) is False
    blob, summary = fake_result()
    queue.complete(job_id, claimed.lease_token, blob, summary)
    job = queue.get(owner, job_id)
    assert job.state == "SUCCEEDED" and job.summary == summary and job.finished_at is not None
    # A finished job shows done: no last window or ETA left over from its computation.
    assert job.progress == {"evaluations": 40, "fraction": 1.0, "stage": "done", "step": "done", "eta_s": 0.0}
    assert queue.get_result(owner, job_id) == (blob, summary)
    kinds = [e.kind for e in queue.events(owner, job_id)]
    assert kinds == ["submitted", "claimed", "progress", "succeeded"]
    assert queue.events(owner, job_id)[2].detail == {"progress": progress}
    assert queue.claim("w2") is None
    # The finished lease is spent: nothing more can be written with it.
    with pytest.raises(LeaseLostError):
        queue.heartbeat(job_id, claimed.lease_token)


def test_claim_order_is_priority_then_age(queue: JobQueue, owner: str) -> None:
    low_old = submit_tiny(queue, owner, seed=1, priority=0)
    high = submit_tiny(queue, owner, seed=2, priority=5)
    low_new = submit_tiny(queue, owner, seed=3, priority=0)
    order = [c.job_id for c in (queue.claim("w"), queue.claim("w"), queue.claim("w")) if c is not None]
    assert order == [high, low_old, low_new]


def test_expired_lease_is_requeued_and_old_token_cannot_write(queue: JobQueue, owner: str) -> None:
    job_id = submit_tiny(queue, owner)
    first = queue.claim("w-dead", lease_seconds=5)
    assert first is not None
    assert queue.requeue_expired(now=utcnow()) == 0  # lease still valid
    later = utcnow() + timedelta(seconds=6)
    assert queue.requeue_expired(now=later) == 1
    job = queue.get(owner, job_id)
    assert job.state == "QUEUED" and job.attempt == 2 and job.errors[0]["attempt"] == 1
    # Backoff: retry_backoff_seconds * 2**(1-1) = 2 s after the requeue.
    assert queue.claim("w-new", now=later + timedelta(seconds=1)) is None
    second = queue.claim("w-new", now=later + timedelta(seconds=2.5))
    assert second is not None and second.attempt == 2 and second.lease_token != first.lease_token
    blob, summary = fake_result()
    with pytest.raises(LeaseLostError):
        queue.heartbeat(job_id, first.lease_token)
    with pytest.raises(LeaseLostError):
        queue.complete(job_id, first.lease_token, blob, summary)
    with pytest.raises(LeaseLostError):
        queue.fail(job_id, first.lease_token, "late failure")
    queue.complete(job_id, second.lease_token, blob, summary)
    assert queue.get(owner, job_id).state == "SUCCEEDED"


def test_heartbeat_renews_a_lease_that_ran_out_but_was_not_requeued_yet(queue: JobQueue, owner: str) -> None:
    # Until the reaper requeues it the token still holds the job and nobody else can claim it, so a worker that
    # was late (a long GC pause, a slow database) keeps its job instead of doing the work twice.
    job_id = submit_tiny(queue, owner)
    claimed = queue.claim("w-slow", lease_seconds=5, now=utcnow() - timedelta(seconds=10))
    assert claimed is not None
    assert queue.heartbeat(job_id, claimed.lease_token) is False
    assert queue.requeue_expired(now=utcnow()) == 0
    assert queue.get(owner, job_id).state == "RUNNING" and queue.claim("w-other") is None
    blob, summary = fake_result()
    queue.complete(job_id, claimed.lease_token, blob, summary)
    assert queue.get(owner, job_id).attempt == 1


def test_retry_exhaustion_fails_with_error_history_then_manual_retry(queue: JobQueue, owner: str) -> None:
    job_id = submit_tiny(queue, owner)
    now = utcnow()
    for attempt in (1, 2, 3):  # max_attempts = 3
        claimed = queue.claim("w", lease_seconds=1, now=now)
        assert claimed is not None and claimed.attempt == attempt
        now += timedelta(seconds=60)  # past the lease
        assert queue.requeue_expired(now=now) == 1
        now += timedelta(seconds=60)  # past the backoff
    job = queue.get(owner, job_id)
    assert job.state == "FAILED" and job.attempt == 3
    assert [e["attempt"] for e in job.errors] == [1, 2, 3]
    assert all("lease expired" in e["error"] for e in job.errors)
    assert queue.claim("w", now=now) is None
    retried = queue.retry(owner, job_id)
    assert retried.state == "QUEUED" and retried.attempt == 1 and len(retried.errors) == 3
    with pytest.raises(ConflictError):
        queue.retry(owner, job_id)


def test_retryable_failure_backs_off_and_fatal_failure_fails(queue: JobQueue, owner: str) -> None:
    job_id = submit_tiny(queue, owner)
    claimed = queue.claim("w")
    assert claimed is not None
    queue.fail(job_id, claimed.lease_token, "worker out of memory", retryable=True)
    job = queue.get(owner, job_id)
    assert job.state == "QUEUED" and job.attempt == 2 and job.not_before is not None
    claimed = queue.claim("w", now=job.not_before + timedelta(seconds=0.1))
    assert claimed is not None
    queue.fail(job_id, claimed.lease_token, "simulation diverged")
    job = queue.get(owner, job_id)
    assert job.state == "FAILED" and [e["error"] for e in job.errors] == ["worker out of memory", "simulation diverged"]


def test_cancel_in_every_state(queue: JobQueue, owner: str) -> None:
    queued = submit_tiny(queue, owner, seed=1)
    assert queue.cancel(owner, queued).state == "CANCELLED"
    assert queue.cancel(owner, queued).state == "CANCELLED"  # idempotent
    assert queue.claim("w") is None

    running = submit_tiny(queue, owner, seed=2)
    lease = queue.claim("w")
    assert lease is not None
    job = queue.cancel(owner, running)
    assert job.state == "RUNNING" and job.cancel_requested
    assert queue.heartbeat(running, lease.lease_token) is True
    queue.acknowledge_cancel(running, lease.lease_token)
    assert queue.get(owner, running).state == "CANCELLED"
    with pytest.raises(LeaseLostError):
        queue.heartbeat(running, lease.lease_token)

    done = submit_tiny(queue, owner, seed=3)
    lease = queue.claim("w")
    assert lease is not None
    queue.complete(done, lease.lease_token, *fake_result())
    with pytest.raises(ConflictError):
        queue.cancel(owner, done)

    failed = submit_tiny(queue, owner, seed=4)
    lease = queue.claim("w")
    assert lease is not None
    queue.fail(failed, lease.lease_token, "boom")
    with pytest.raises(ConflictError):
        queue.cancel(owner, failed)


def test_release_returns_job_without_consuming_an_attempt(queue: JobQueue, owner: str) -> None:
    job_id = submit_tiny(queue, owner)
    lease = queue.claim("w")
    assert lease is not None
    queue.release(job_id, lease.lease_token)
    job = queue.get(owner, job_id)
    assert job.state == "QUEUED" and job.attempt == 1
    again = queue.claim("w")
    assert again is not None and again.attempt == 1


def test_owner_scoping_delete_and_keys(queue: JobQueue, keys: ApiKeyStore, owner: str) -> None:
    other, other_plain = keys.create("someone else")
    assert keys.authenticate(other_plain) == other
    with pytest.raises(AuthenticationError):
        keys.authenticate(other_plain + "x")
    job_id = submit_tiny(queue, owner)
    for action in (queue.get, queue.cancel, queue.retry, queue.delete, queue.get_result, queue.events):
        with pytest.raises(NotFoundError):
            action(other, job_id)
    with pytest.raises(ConflictError):
        queue.delete(owner, job_id)  # still QUEUED
    queue.cancel(owner, job_id)
    queue.delete(owner, job_id)
    with pytest.raises(NotFoundError):
        queue.get(owner, job_id)
    assert [e.kind for e in queue.events(None, job_id)][-1] == "deleted"
    assert {k.name for k in keys.list()} == {"tests", "someone else"}


def test_idempotency_and_active_job_limit(queue: JobQueue, owner: str) -> None:
    first, created = queue.submit(owner, tiny_payload(1), JobOptions(seed=1), "key-1", "a", 5)
    again, created_again = queue.submit(owner, tiny_payload(1), JobOptions(seed=1), "key-1", "a", 5)
    assert created and not created_again and again.id == first.id
    with pytest.raises(IdempotencyMismatchError):
        queue.submit(owner, tiny_payload(1), JobOptions(seed=2), "key-1", "a", 5)
    queue.settings = queue.settings.model_copy(update={"max_active_jobs_per_key": 2})
    submit_tiny(queue, owner, seed=2)
    with pytest.raises(LimitExceededError) as info:
        submit_tiny(queue, owner, seed=3)
    assert info.value.retry_after == queue.settings.active_jobs_retry_after_seconds
    assert queue.count_active(owner) == 2


def test_a_job_stored_before_defaults_left_the_hash_still_matches_its_key(queue: JobQueue, owner: str) -> None:
    """Jobs queued by an older release hold the hash over every option; re-sending their key must still find them."""
    payload, options = tiny_payload(1), JobOptions(seed=1)
    first, _ = queue.submit(owner, payload, options, "key-old", "a", 5)
    assert first.payload_hash == payload_hash(payload, options) != legacy_payload_hash(payload, options)
    with queue.tx.write() as conn:
        conn.execute(
            sa.update(jobs).where(jobs.c.id == first.id).values(payload_hash=legacy_payload_hash(payload, options))
        )
    again, created = queue.submit(owner, payload, options, "key-old", "a", 5)
    assert not created and again.id == first.id
    with pytest.raises(IdempotencyMismatchError):
        queue.submit(owner, payload, JobOptions(seed=2), "key-old", "a", 5)


def test_keyset_pagination_and_state_filter(queue: JobQueue, owner: str) -> None:
    ids = [submit_tiny(queue, owner, seed=i) for i in range(7)]
    queue.cancel(owner, ids[0])
    seen: list[str] = []
    token = None
    while True:
        page, token = queue.list(owner, page_size=3, page_token=token)
        seen += [j.id for j in page]
        if token is None:
            break
    assert seen == ids[::-1]
    cancelled, _ = queue.list(owner, state="CANCELLED")
    assert [j.id for j in cancelled] == [ids[0]]
    with pytest.raises(InvalidRequestError):
        queue.list(owner, page_token="not-a-token")
    stats = queue.stats()
    assert stats.jobs_by_state == {"QUEUED": 6, "CANCELLED": 1} and stats.claims_total == 0


def test_a_batch_id_no_batch_can_have_finds_nothing(queue: JobQueue, owner: str) -> None:
    """A NUL or other text no batch id holds is answered as a missing batch without reaching the database
    (PostgreSQL refuses to compare a NUL: a server error before)."""
    batch = queue.create_batch(owner, "b")
    queue.submit(owner, tiny_payload(0), JobOptions(), None, "in-batch", 5, batch_id=batch.id)
    assert [j.name for j in queue.list(owner, batch_id=batch.id)[0]] == ["in-batch"]
    for odd in ("ý\x00sk", "a b", "x" * 65):
        assert queue.list(owner, batch_id=odd) == ([], None)
        with pytest.raises(NotFoundError):
            queue.get_batch(owner, odd)
