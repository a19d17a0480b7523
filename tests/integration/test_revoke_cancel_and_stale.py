"""Issue #16, queue side (SQLite and PostgreSQL): ``keys revoke --cancel-jobs`` cancels the key's QUEUED
jobs and flags its RUNNING ones; a dead deployment's RUNNING jobs are requeued by worker-id prefix; the
development key of ``up`` is reused while valid."""

from __future__ import annotations

from pathlib import Path

import pytest

from common.api_key_store import ApiKeyStore
from common.cli import main
from common.queue import JobQueue
from common.settings import get_settings
from tests.support.queue_fixtures import BACKENDS, submit_tiny
from worker.runtime.deployment_state import DeploymentRecord, DeploymentState
from worker.runtime.supervisor import development_key

pytestmark = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)


def test_revoke_with_cancel_jobs(
    queue: JobQueue,
    keys: ApiKeyStore,
    db_url: str,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    doomed, _ = keys.create("doomed")
    other, _ = keys.create("other")
    queued = [submit_tiny(queue, doomed, seed=i) for i in range(2)]
    running = submit_tiny(queue, doomed, seed=5, priority=10)
    kept = submit_tiny(queue, other, seed=6)
    lease = queue.claim("w1")
    assert lease is not None and lease.job_id == running

    monkeypatch.setenv("HOI_REFINE_DATABASE_URL", db_url)
    get_settings.cache_clear()
    assert main(["keys", "revoke", "doomed", "--cancel-jobs"]) == 0
    assert "2 queued cancelled, 1 running asked to stop" in capsys.readouterr().out
    assert [queue.get(None, j).state for j in queued] == ["CANCELLED", "CANCELLED"]
    assert queue.get(None, running).cancel_requested and queue.get(None, running).state == "RUNNING"
    assert queue.heartbeat(running, lease.lease_token) is True  # the worker sees the flag and stops
    assert queue.get(None, kept).state == "QUEUED" and not queue.get(None, kept).cancel_requested
    kinds = [e.kind for e in queue.events(None, queued[0])]
    assert kinds[-1] == "cancelled"
    # Again (the key already revoked): no QUEUED job is left; the RUNNING one is flagged again, harmlessly.
    assert queue.cancel_jobs_of_key(doomed) == (0, 1)


def test_dead_deployment_jobs_are_requeued_by_worker_prefix(queue: JobQueue, owner: str) -> None:
    mine = [submit_tiny(queue, owner, seed=i) for i in range(2)]
    theirs = submit_tiny(queue, owner, seed=9)
    record = DeploymentRecord(supervisor_pid=4242, host="host_a%", url="http://x")
    for _ in mine:
        assert queue.claim(f"{record.worker_prefix}1-abc") is not None
    assert queue.claim("host_a%-42420-w1-def") is not None  # another supervisor: pid 42420, not 4242
    assert queue.requeue_worker_jobs(record.worker_prefix, "the up running it died") == 2
    for job in mine:
        rec = queue.get(None, job)
        assert rec.state == "QUEUED" and rec.attempt == 2 and "died" in rec.errors[-1]["error"]
    assert queue.get(None, theirs).state == "RUNNING"


def test_development_key_is_reused_until_revoked(db_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HOI_REFINE_DATABASE_URL", db_url)
    get_settings.cache_clear()
    state = DeploymentState(tmp_path / "var")
    state.dir.mkdir(parents=True)
    first = development_key(state, "dev")
    assert development_key(state, "dev") == first
    assert (state.dir / "up-dev-key").stat().st_mode & 0o777 == 0o600
    assert main(["keys", "revoke", first]) == 0
    second = development_key(state, "dev")
    assert second != first and development_key(state, "dev") == second


def test_key_names_with_nul_or_controls_are_refused_on_every_database(keys: ApiKeyStore) -> None:
    from common.errors import InvalidRequestError

    for bad in ("a\x00b", "bell\x07", "\u202eevil"):
        with pytest.raises(InvalidRequestError, match="name"):
            keys.create(bad)
    assert [k.name for k in keys.list()] == []
