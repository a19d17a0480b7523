"""Issue #5 acceptance: ``hoi-refine up --workers 2`` survives a killed worker and honours cancel and Ctrl-C.

On SQLite, and again on PostgreSQL when it answers: 4 short sequences are submitted over HTTP; one worker
process is SIGKILLed in the middle of a job; all 4 reach SUCCEEDED, the killed job with attempt 2, each
result is stored once and equals a local ``refine_sequence`` of the same payload, options and seed. A
cancel sent to a running job ends it CANCELLED within one generation (plus one heartbeat interval), and
SIGINT to ``up`` while a job runs leaves it QUEUED, not RUNNING.
"""

from __future__ import annotations

import os
import signal
import socket
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.api_client import ApiClient
from common.database import create_engine_for
from common.job_options import JobOptions
from common.queue import JobQueue
from common.result_format import read_arrays
from common.sequence_io import sequence_from_npz_bytes, sequence_to_npz_bytes
from tests.support.queue_fixtures import BACKENDS
from worker.runtime.demo_client import local_deployment

pytestmark = pytest.mark.slow

LEASE_S = 4.0
SHORT = JobOptions(max_generations=3, popsize=8)
LONG = JobOptions(max_generations=400, popsize=8)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_for(client: ApiClient, job_id: str, pred: Any, timeout: float, what: str) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job, _ = client.job(job_id)
        if pred(job):
            return job
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}; last: {job['state']} {job.get('progress')}")


def _running_with_progress(job: dict[str, Any]) -> bool:
    p = job.get("progress") or {}
    return job["state"] == "RUNNING" and bool(p.get("evaluations")) and "pid" in p


def _arrays(blob: bytes) -> dict[str, np.ndarray]:
    return read_arrays(blob)  # every array; the summary and the wall-clock timings are not arrays


@pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)
def test_up_two_workers_crash_cancel_and_stop(db_url: str, tmp_path: Path) -> None:
    log = tmp_path / "up.log"
    try:
        _scenario(db_url, tmp_path, log)
    except Exception as exc:
        tail = log.read_text(errors="replace")[-6000:] if log.exists() else "(no log)"
        raise AssertionError(f"{exc!r}\n--- hoi-refine up log (tail) ---\n{tail}") from exc


def _scenario(db_url: str, tmp_path: Path, log: Path) -> None:
    from worker.example.sequences import short_example_sequence
    from worker.refine.run import refine_sequence

    env = {
        **os.environ,
        "HOI_REFINE_DATABASE_URL": db_url,
        "HOI_REFINE_VAR_DIR": str(tmp_path / "var"),
        "HOI_REFINE_LEASE_SECONDS": str(LEASE_S),
        "HOI_REFINE_RETRY_BACKOFF_SECONDS": "0",
    }
    queue = JobQueue(create_engine_for(db_url))
    payloads = [sequence_to_npz_bytes(short_example_sequence(seed=i)) for i in range(4)]
    with local_deployment(log, workers=2, threads_per_worker=1, port=_free_port(), env=env) as dep:
        client = ApiClient(dep.base_url, dep.api_key)
        ids = [client.submit(p, f"{i}.npz", SHORT.model_copy(update={"seed": i}))["id"] for i, p in enumerate(payloads)]

        # SIGKILL the worker process of the first job to show progress, in the middle of that job.
        victim_job = None
        deadline = time.monotonic() + 120
        while victim_job is None and time.monotonic() < deadline:
            victim_job = next((j for j, _ in map(client.job, ids) if _running_with_progress(j)), None)
            time.sleep(0.05)
        assert victim_job is not None, "no job reported progress"
        victim_pid = int(victim_job["progress"]["pid"])
        assert victim_pid != dep.process.pid
        os.kill(victim_pid, signal.SIGKILL)

        done = [_wait_for(client, i, lambda j: j["state"] in ("SUCCEEDED", "FAILED"), 240, "job end") for i in ids]
        assert [j["state"] for j in done] == ["SUCCEEDED"] * 4, [j.get("errors") for j in done]
        attempts = {j["id"]: j["attempt"] for j in done}
        assert attempts[victim_job["id"]] == 2
        assert sorted(attempts.values()) == [1, 1, 1, 2]
        results = {i: client.result(i) for i in ids}

        # Cancel a running job: it ends CANCELLED long before its generations are spent (work is counted, not
        # timed: a busy machine must not fail this).
        long_jobs = (client.submit(payloads[0], f"long{s}.npz", LONG.model_copy(update={"seed": s})) for s in (7, 8))
        cancel_id, stop_id = (job["id"] for job in long_jobs)
        _wait_for(client, cancel_id, _running_with_progress, 60, "the long job to run")
        client.cancel(cancel_id)
        _wait_for(client, cancel_id, lambda j: j["state"] == "CANCELLED", 60, "CANCELLED")
        kinds = [e.kind for e in queue.events(None, cancel_id)]
        assert kinds[-1] == "cancelled" and "succeeded" not in kinds

        # Ctrl-C while a job runs: the worker releases it (leaving the with-block sends SIGINT to `up`).
        _wait_for(client, stop_id, _running_with_progress, 60, "the second long job to run")
        client.close()
    assert dep.process.returncode == 0, log.read_text()[-3000:]
    stopped = queue.get(None, stop_id)
    assert stopped.state == "QUEUED" and stopped.attempt == 1

    for i, job_id in enumerate(ids):
        kinds = [e.kind for e in queue.events(None, job_id)]
        assert kinds.count("succeeded") == 1, kinds  # the result was written exactly once
        if job_id == victim_job["id"]:
            assert kinds.count("requeued") == 1 and kinds.count("claimed") == 2
        # Same payload, options and seed, refined here in this process: the same trajectories and controls.
        stored = queue.get_payload(job_id)
        local = refine_sequence(sequence_from_npz_bytes(stored), SHORT.model_copy(update={"seed": i}), threads=1)
        remote, mine = _arrays(results[job_id]), _arrays(local.to_npz_bytes())
        assert remote.keys() == mine.keys() and {"object_pose_sim", "right_q_target"} <= mine.keys()
        for key in mine:
            np.testing.assert_array_equal(remote[key], mine[key], err_msg=key)
    text = log.read_text()
    assert "Ray restarts it" in text
    assert "hoi-refine up: stopped" in text
