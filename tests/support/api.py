"""Request bodies and constants for the API tests."""

from __future__ import annotations

import time
from typing import Any

from common.queue import JobQueue
from common.sequence_io import sequence_to_json_dict
from tests.support.queue_fixtures import fake_result, tiny_sequence

PROBLEM = "application/problem+json"


def json_body(seed: int = 0, frames: int = 5, **options: object) -> dict[str, object]:
    body = sequence_to_json_dict(tiny_sequence(seed, frames).validate())
    body["options"] = {"seed": seed, **options}
    return body


def run_job(queue: JobQueue, job_id: str) -> None:
    lease = queue.claim("w")
    assert lease is not None and lease.job_id == job_id
    queue.complete(job_id, lease.lease_token, *fake_result())


def wait_until(condition: Any, what: str, timeout: float = 60.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := condition():
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")
