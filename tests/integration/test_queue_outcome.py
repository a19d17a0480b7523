"""The job's outcome in the queue (issue #53 item 1) on SQLite and PostgreSQL: set with the result, listed and
counted per outcome for jobs and batches, files listed beside a SUCCEEDED job; jobs finished before the
outcome column existed read ``unknown`` after the migration."""

from __future__ import annotations

from typing import Any

import pytest
import sqlalchemy as sa
from alembic import command

from common.database import alembic_config, create_engine_for, upgrade_to_head
from common.errors import InvalidRequestError
from common.job_options import JobOptions
from common.queue import JobQueue
from common.queue_types import Artifact
from tests.support.queue_fixtures import BACKENDS, fake_result, tiny_payload

pytestmark = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)

REASON = {"code": "hand_never_touches", "frame": None, "value": None, "unit": None,
          "message": "no finger touches the object in any frame"}  # fmt: skip


def summary(executable: bool | None) -> dict[str, Any]:
    doc: dict[str, Any] = {"metrics": {"raw": {"E_t": 2.0}, "refined": {"E_t": 0.5, "E_r": 2.0,
                                                                          "paper": {"E_t": 0.7, "E_r": 2.5}}}}
    if executable is not None:
        doc["outcome"] = {"executable": executable, "protocol": "paper", "reasons": [] if executable else [REASON]}
    return doc


def finish(queue: JobQueue, job_id: str, doc: dict[str, Any] | None, files: tuple[Artifact, ...] = ()) -> None:
    lease = queue.claim("w")
    assert lease is not None and lease.job_id == job_id
    if doc is None:
        queue.fail(job_id, lease.lease_token, "diverged")
    else:
        queue.complete(job_id, lease.lease_token, fake_result()[0], doc, files)


def test_outcome_is_stored_with_the_result_and_filters_jobs_and_batches(queue: JobQueue, owner: str) -> None:
    batch = queue.create_batch(owner, "b")
    other = queue.create_batch(owner, "all good")
    good = queue.submit(owner, *_tiny(9), batch_id=other.id)[0].id
    ids = [queue.submit(owner, *_tiny(i), batch_id=batch.id)[0].id for i in range(5)]
    video = Artifact("video.mp4", "video/mp4", b"\x00" * 10)
    plot = Artifact("plots/errors.png", "image/png", b"\x89PNG")
    finish(queue, good, summary(True))  # claimed oldest first
    finish(queue, ids[0], summary(True), (video, plot))
    finish(queue, ids[1], summary(False))
    finish(queue, ids[2], summary(None))  # a result without an outcome
    finish(queue, ids[3], None)  # FAILED: no outcome

    job = queue.get(owner, ids[1])
    assert job.outcome == "not_executable"
    assert job.outcome_detail == {"protocol": "paper", "reasons": [REASON], "reasons_total": 1,
                                  "protocol_metrics": "paper", "E_t": 0.7, "E_r": 2.5}  # fmt: skip
    assert queue.get(owner, ids[2]).outcome == "unknown" and queue.get(owner, ids[3]).outcome is None
    assert queue.get(owner, ids[4]).outcome is None  # still QUEUED
    assert [(f.name, f.content_type, f.size_bytes) for f in queue.get(owner, ids[0]).files] == [
        ("plots/errors.png", "image/png", 4), ("video.mp4", "video/mp4", 10)]  # fmt: skip

    def listed(**kw: Any) -> set[str]:
        return {j.id for j in queue.list(owner, **kw)[0]}

    assert listed(outcome="executable") == {ids[0], good}
    assert listed(outcome="executable", batch_id=batch.id) == {ids[0]}
    assert listed(outcome="not_executable") == {ids[1]} and listed(outcome="unknown") == {ids[2]}
    page = {j.id: j for j in queue.list(owner, batch_id=batch.id)[0]}
    assert page[ids[0]].files == queue.get(owner, ids[0]).files and page[ids[1]].files == ()
    assert page[ids[1]].outcome_detail == job.outcome_detail and page[ids[1]].summary is None

    counted = queue.get_batch(owner, batch.id)
    assert counted.outcomes == {"executable": 1, "not_executable": 1, "unknown": 1}
    assert counted.counts["SUCCEEDED"] == 3 and counted.counts["FAILED"] == 1 and counted.counts["QUEUED"] == 1
    assert {b.id: b.outcomes for b in queue.list_batches(owner)[0]}[other.id] == {
        "executable": 1, "not_executable": 0, "unknown": 0}  # fmt: skip
    assert [b.id for b in queue.list_batches(owner, outcome="not_executable")[0]] == [batch.id]
    assert {b.id for b in queue.list_batches(owner, outcome="executable")[0]} == {batch.id, other.id}
    with pytest.raises(InvalidRequestError):
        queue.list(owner, outcome="fine")


def _tiny(seed: int) -> tuple[bytes, JobOptions, None, str, int]:
    return tiny_payload(seed), JobOptions(seed=seed), None, f"tiny-{seed}", 5


def test_the_migration_marks_jobs_that_succeeded_before_it_unknown(empty_db_url: str) -> None:
    command.upgrade(alembic_config(empty_db_url), "0003_batches_events")
    engine = create_engine_for(empty_db_url)
    try:
        with engine.begin() as conn:
            conn.execute(sa.text("INSERT INTO api_keys (id, name, key_hash, prefix, created_at) "
                                 "VALUES ('k', 'k', 'h', 'p', CURRENT_TIMESTAMP)"))  # fmt: skip
            for job_id, state in (("done", "SUCCEEDED"), ("waiting", "QUEUED"), ("broken", "FAILED")):
                conn.execute(
                    sa.text(
                        "INSERT INTO jobs (id, owner_key_id, name, state, priority, attempt, payload_hash, options, "
                        "num_frames, cancel_requested, errors, created_at, queued_at, updated_at) VALUES "
                        "(:id, 'k', :id, :state, 0, 1, 'h', '{}', 5, false, '[]', CURRENT_TIMESTAMP, "
                        "CURRENT_TIMESTAMP, CURRENT_TIMESTAMP)"
                    ),
                    {"id": job_id, "state": state},
                )
        upgrade_to_head(empty_db_url)
        with engine.connect() as conn:
            rows: dict[str, str | None] = dict(conn.execute(sa.text("SELECT id, outcome FROM jobs")).all())
        assert rows == {"done": "unknown", "waiting": None, "broken": None}
        queue = JobQueue(engine)
        assert queue.get("k", "done").outcome == "unknown" and queue.get("k", "done").outcome_detail is None
        assert [j.id for j in queue.list("k", outcome="unknown")[0]] == ["done"]
    finally:
        engine.dispose()

