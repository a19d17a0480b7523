"""Server-sent events on SQLite and PostgreSQL, over a real loopback socket (uvicorn in a thread): a job's
stream delivers QUEUED -> RUNNING -> progress -> SUCCEEDED while a worker (driven through ``JobQueue``)
moves it, ends when the job is finished, and resumes after ``Last-Event-ID``; a batch stream covers all
of its jobs and ends when the batch is COMPLETED."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from common.database import create_engine_for
from common.queue import JobQueue
from common.settings import Settings
from service.app import create_app
from tests.support.api import json_body
from tests.support.live_server import serve_app
from tests.support.queue_fixtures import BACKENDS, fake_result

pytestmark = pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)

SSE = {"Accept": "text/event-stream"}


@pytest.fixture
def live(db_url: str) -> Iterator[tuple[str, JobQueue, dict[str, str]]]:
    settings = Settings(events_poll_seconds=0.05, events_heartbeat_seconds=0.2, max_active_jobs_per_key=50)
    engine = create_engine_for(db_url)
    app = create_app(settings, engine)
    queue: JobQueue = app.state.queue
    _, key = app.state.api_keys.create("events")
    with serve_app(app) as base:
        yield base, queue, {"Authorization": f"Bearer {key}"}
    engine.dispose()


def read_events(resp: httpx.Response, on_event: Any = None) -> list[dict[str, Any]]:
    """Parse an event stream until the server ends it: [{id, event, data}], comments counted as keep-alives."""
    out: list[dict[str, Any]] = []
    current: dict[str, Any] = {}
    for line in resp.iter_lines():
        if line.startswith(":"):
            out.append({"event": "comment"})
        elif line.startswith("id: "):
            current["id"] = int(line[4:])
        elif line.startswith("event: "):
            current["event"] = line[7:]
        elif line.startswith("data: "):
            current["data"] = json.loads(line[6:])
        elif line == "" and current:
            out.append(current)
            if on_event is not None:
                on_event(current)
            current = {}
    return out


def test_job_stream_follows_the_job_live_and_resumes_after_last_event_id(
    live: tuple[str, JobQueue, dict[str, str]],
) -> None:
    base, queue, auth = live
    job_id = httpx.post(f"{base}/v1/jobs", json=json_body(), headers=auth).json()["id"]
    first_seen = threading.Event()
    errors: list[BaseException] = []

    def worker() -> None:
        try:
            assert first_seen.wait(30)
            lease = queue.claim("w1")
            assert lease is not None
            queue.heartbeat(job_id, lease.lease_token, {"window": 1, "windows": 3})
            queue.heartbeat(job_id, lease.lease_token, {"window": 2, "windows": 3})
            queue.complete(job_id, lease.lease_token, *fake_result())
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=worker)
    thread.start()
    with httpx.stream("GET", f"{base}/v1/jobs/{job_id}/events", headers={**auth, **SSE}, timeout=60) as resp:
        assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/event-stream")
        events = read_events(resp, lambda e: first_seen.set())
    thread.join(30)
    assert not errors, errors
    real = [e for e in events if e["event"] != "comment"]
    states = [e["data"]["state"] for e in real if e["event"] == "state"]
    assert states == ["QUEUED", "RUNNING", "SUCCEEDED"]
    assert [e["data"]["progress"]["window"] for e in real if e["event"] == "progress"] == [1, 2]
    assert [e["event"] for e in real] == ["state", "state", "progress", "progress", "state", "end"]
    assert real[-1]["data"]["state"] == "SUCCEEDED" and "id" not in real[-1]
    ids = [e["id"] for e in real[:-1]]
    assert ids == sorted(ids) and len(set(ids)) == len(ids)

    # Reconnect after the RUNNING event: only what came after it, then the end.
    resumed_from = real[1]["id"]
    headers = {**auth, **SSE, "Last-Event-ID": str(resumed_from)}
    with httpx.stream("GET", f"{base}/v1/jobs/{job_id}/events", headers=headers, timeout=60) as resp:
        again = [e for e in read_events(resp) if e["event"] != "comment"]
    assert [e.get("id") for e in again] == [*ids[2:], None]
    # Without the Accept header the same URL still answers the JSON list.
    listed = httpx.get(f"{base}/v1/jobs/{job_id}/events", headers=auth).json()["events"]
    assert [e["id"] for e in listed] == ids
    bad = httpx.get(f"{base}/v1/jobs/{job_id}/events", headers={**auth, **SSE, "Last-Event-ID": "x"})
    assert bad.status_code == 422
    assert httpx.get(f"{base}/v1/jobs/nope/events", headers={**auth, **SSE}).status_code == 404


def test_batch_stream_covers_its_jobs_and_ends_when_the_batch_is_completed(
    live: tuple[str, JobQueue, dict[str, str]],
) -> None:
    base, queue, auth = live
    batch_id = httpx.post(f"{base}/v1/batches", json={"name": "b"}, headers=auth).json()["id"]
    ids = [httpx.post(f"{base}/v1/jobs", json={**json_body(i), "batch_id": batch_id}, headers=auth).json()["id"]
           for i in range(2)]  # fmt: skip
    outside = httpx.post(f"{base}/v1/jobs", json=json_body(7), headers=auth).json()["id"]
    seen = threading.Event()

    def worker() -> None:
        assert seen.wait(30)
        for _ in range(3):
            lease = queue.claim("w")
            assert lease is not None
            if lease.job_id == ids[1]:
                queue.fail(lease.job_id, lease.lease_token, "diverged")
            else:
                queue.complete(lease.job_id, lease.lease_token, *fake_result())

    thread = threading.Thread(target=worker)
    thread.start()
    with httpx.stream("GET", f"{base}/v1/batches/{batch_id}/events", headers=auth, timeout=60) as resp:
        events = [e for e in read_events(resp, lambda e: seen.set()) if e["event"] != "comment"]
    thread.join(30)
    assert {e["data"]["job_id"] for e in events[:-1]} == set(ids) and outside not in str(events)
    by_job = {j: [e["data"]["state"] for e in events if e.get("data", {}).get("job_id") == j] for j in ids}
    assert by_job == {ids[0]: ["QUEUED", "RUNNING", "SUCCEEDED"], ids[1]: ["QUEUED", "RUNNING", "FAILED"]}
    end = events[-1]
    assert end["event"] == "end" and end["data"]["state"] == "COMPLETED"
    assert end["data"]["counts"]["SUCCEEDED"] == 1 and end["data"]["counts"]["FAILED"] == 1
