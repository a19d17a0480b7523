"""Bulk submit's HTTP client: retries on 5xx / connection errors, 429 Retry-After, no retry on other 4xx.

A tiny ``httpx.MockTransport`` plays the server (the real server is exercised in the integration test);
waits are recorded instead of slept.
"""

from __future__ import annotations

import email.utils
import io
import threading
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest
from rich.console import Console

from common.api_client import ApiClient, RetryPolicy, Stopped, parse_retry_after
from common.errors import ApiError
from common.job_options import JobOptions


class RecordingStop(threading.Event):
    """A stop flag whose waits return at once and are recorded (the client sleeps through ``stop.wait``)."""

    def __init__(self) -> None:
        super().__init__()
        self.waits: list[float] = []

    def wait(self, timeout: float | None = None) -> bool:
        self.waits.append(float(timeout or 0.0))
        return self.is_set()


def _client(handler: Callable[[httpx.Request], httpx.Response], stop: threading.Event) -> ApiClient:
    return ApiClient(
        "http://api.test",
        "k-123",
        retry=RetryPolicy(max_retries=3, backoff_base_s=0.5, backoff_max_s=4.0),
        stop=stop,
        transport=httpx.MockTransport(handler),
    )


def test_submit_retries_5xx_and_connection_errors_and_honours_429() -> None:
    seen: list[httpx.Request] = []
    script = ["503", "connect", "429", "202"]

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        step = script[len(seen) - 1]
        if step == "connect":
            raise httpx.ConnectError("connection refused", request=request)
        if step == "429":
            return httpx.Response(429, headers={"Retry-After": "7"}, json={"title": "Limit exceeded"})
        if step == "503":
            return httpx.Response(503, json={"title": "Database unavailable"})
        return httpx.Response(202, headers={"Location": "/v1/jobs/j-1"}, json={"id": "j-1", "state": "QUEUED"})

    stop = RecordingStop()
    with _client(handler, stop) as client:
        doc = client.submit(b"NPZ-BYTES", "s.npz", JobOptions(seed=4), key="abc")
    assert doc["id"] == "j-1"
    assert len(seen) == 4
    # Every attempt is the same request: same key, same bytes, same auth.
    assert {r.headers["Idempotency-Key"] for r in seen} == {"abc"}
    assert {r.headers["Authorization"] for r in seen} == {"Bearer k-123"}
    bodies = [r.read() for r in seen]
    assert b"NPZ-BYTES" in bodies[0] and b'"seed":4' in bodies[0]
    # Backoff grows (jittered within [cap/2, cap]); the 429 waits exactly what the server asked.
    assert 0.25 <= stop.waits[0] <= 0.5 and 0.5 <= stop.waits[1] <= 1.0
    assert stop.waits[2] == 7.0
    assert client.retries_made == 2 and client.throttled == 1


def test_gives_up_after_the_retry_budget() -> None:
    calls = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        return httpx.Response(502, text="bad gateway")

    stop = RecordingStop()
    with _client(handler, stop) as client, pytest.raises(ApiError, match="gave up after 4 tries") as err:
        client.job("j-1")
    assert err.value.status == 502
    assert len(calls) == 4  # the first try + max_retries
    assert len(stop.waits) == 3 and 1.0 <= stop.waits[2] <= 2.0  # third backoff: cap 0.5 * 2**2


def test_client_errors_are_not_retried_and_carry_the_problem_detail() -> None:
    calls = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        problem = {"type": "about:blank", "title": "Invalid sequence", "detail": "object_pose: has no frames"}
        return httpx.Response(422, json=problem, headers={"Content-Type": "application/problem+json"})

    with _client(handler, RecordingStop()) as client, pytest.raises(ApiError, match="has no frames") as err:
        client.submit(b"x", "s.npz", JobOptions(), key="k")
    assert err.value.status == 422 and err.value.problem["title"] == "Invalid sequence"
    assert len(calls) == 1


def test_job_id_from_location_when_the_body_has_none() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(202, headers={"Location": "http://api.test/v1/jobs/42"})

    with _client(handler, RecordingStop()) as client:
        assert client.submit(b"x", "s.npz", JobOptions(), key="k")["id"] == "42"


def test_stop_ends_a_retry_wait() -> None:
    stop = RecordingStop()

    def handler(request: httpx.Request) -> httpx.Response:
        stop.set()  # Ctrl-C arrives while the server is failing
        return httpx.Response(500)

    with _client(handler, stop) as client, pytest.raises(Stopped):
        client.job("j")


def test_parse_retry_after() -> None:
    assert parse_retry_after("5") == 5.0
    assert parse_retry_after(None) is None and parse_retry_after("soon") is None
    later = email.utils.formatdate(time.time() + 30, usegmt=True)
    assert 25 <= (parse_retry_after(later) or 0) <= 31
    assert parse_retry_after(email.utils.formatdate(time.time() - 30, usegmt=True)) == 0.0


def test_a_run_stops_once_retries_are_spent_instead_of_trying_every_sequence(tmp_path: Path) -> None:
    from common.sequence_io import save_sequence
    from service.submit.runner import SubmitConfig, run_submit
    from tests.support.queue_fixtures import tiny_sequence

    for i in range(3):
        save_sequence(tiny_sequence(seed=i), tmp_path / f"s{i}.npz")
    calls: list[httpx.Request] = []

    def down(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/batches":  # a server without batches: the run goes on without one
            return httpx.Response(404, json={"title": "Not Found"})
        calls.append(request)
        return httpx.Response(503, json={"title": "Database unavailable"})

    client = ApiClient("http://api.test", "k", retry=RetryPolicy(max_retries=2, backoff_base_s=0.001),
                       transport=httpx.MockTransport(down))  # fmt: skip
    log = io.StringIO()
    cfg = SubmitConfig(paths=[tmp_path], api_url="http://api.test", api_key="k", out_dir=tmp_path / "out",
                       concurrency=1)  # fmt: skip
    outcome = run_submit(cfg, client=client, console=Console(file=log, width=300))
    assert len(calls) == 3  # one sequence: the first try + 2 retries; the other two were never sent
    assert outcome.exit_code == 1 and not outcome.interrupted
    assert [e.posts for e in outcome.entries] == [1, 0, 0]
    assert all(e.state == "PENDING" for e in outcome.entries)
    assert "the service keeps failing" in log.getvalue() and "HTTP 503" in log.getvalue()
