"""Issue #16: ``hoi-refine up`` survives its own API's death and its own SIGKILL.

One deployment (self-test jobs, no physics): its API child is SIGKILLed and ``up`` restarts it by itself;
then a job is RUNNING when the whole process group of ``up`` is SIGKILLed. The API child (in its own
session) must die with it (``PR_SET_PDEATHSIG``), a second ``up`` on the same var dir and port must start,
clear the dead deployment, reuse its development key, and the job must finish (attempt 2) long before
its 60 s lease would have run out.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from common.api_client import ApiClient
from common.job_options import JobOptions
from tests.support.queue_fixtures import BACKENDS, tiny_payload
from worker.runtime.demo_client import local_deployment
from worker.runtime.deployment_state import process_start_time

pytestmark = pytest.mark.slow

LEASE_S = 60.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _until(pred: Any, timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            value = pred()
        except (httpx.HTTPError, OSError, ValueError, KeyError):
            value = None
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


def _record(var_dir: Path) -> dict[str, Any]:
    return dict(json.loads((var_dir / "up.json").read_text()))


def _gone(pid: int) -> bool:
    return process_start_time(pid) is None or "Z" in Path(f"/proc/{pid}/stat").read_text().split(")")[1][:3]


@pytest.mark.parametrize("empty_db_url", BACKENDS, indirect=True)
def test_api_restarts_and_up_recovers_from_sigkill(db_url: str, tmp_path: Path) -> None:
    var_dir = tmp_path / "var"
    port = _free_port()
    env = {
        **os.environ,
        "HOI_REFINE_DATABASE_URL": db_url,
        "HOI_REFINE_VAR_DIR": str(var_dir),
        "HOI_REFINE_LEASE_SECONDS": str(LEASE_S),
        "HOI_REFINE_RETRY_BACKOFF_SECONDS": "0",
        "HOI_REFINE_SELFTEST_GENERATION_SECONDS": "0.5",
    }
    args = ("--job-kind", "selftest")
    logs = [tmp_path / "up1.log", tmp_path / "up2.log"]
    try:
        with local_deployment(logs[0], workers=1, port=port, env=env, extra_args=args) as first:
            client = ApiClient(first.base_url, first.api_key, timeout_s=10)
            # 1. The API dies: `up` starts another one by itself.
            api_pid = _record(var_dir)["api_pid"]
            os.kill(api_pid, signal.SIGKILL)
            _until(lambda: _record(var_dir)["api_pid"] != api_pid, 60, "a new API process")
            _until(lambda: httpx.get(first.base_url + "/healthz", timeout=2).status_code == 200, 60, "the new API")
            assert first.process.poll() is None, "`up` must survive its API's death"

            # 2. A job runs when the whole process group of `up` is SIGKILLed.
            options = JobOptions(max_generations=16, seed=3)
            job_id = client.submit(tiny_payload(3), "tiny.npz", options)["id"]
            running = lambda: (j := client.job(job_id)[0])["state"] == "RUNNING" and j["progress"]  # noqa: E731
            _until(running, 60, "RUNNING")
            api_pid = _record(var_dir)["api_pid"]
            client.close()
            os.killpg(first.process.pid, signal.SIGKILL)
            first.process.wait(30)
            _until(lambda: _gone(api_pid), 15, "the API child to die with `up`")
            assert (var_dir / "up.json").exists()  # the dead deployment's record stays for the next `up`

        with local_deployment(logs[1], workers=1, port=port, env=env, extra_args=args) as second:
            assert second.api_key == first.api_key  # the development key is reused, so the job stays visible
            client = ApiClient(second.base_url, second.api_key, timeout_s=10)
            job = _until(lambda: (j := client.job(job_id)[0])["state"] in ("SUCCEEDED", "FAILED") and j, 60, "job end")
            assert job["state"] == "SUCCEEDED" and job["attempt"] == 2, job
            assert "died" in job["errors"][0]["error"]  # requeued at start-up as a dead deployment's, not by its lease
            client.close()
        assert second.process.returncode == 0
        assert not (var_dir / "up.json").exists()  # a clean stop leaves no record
    except Exception as exc:
        tails = "\n".join(f"--- {p.name} ---\n{p.read_text(errors='replace')[-4000:]}" for p in logs if p.exists())
        raise AssertionError(f"{exc!r}\n{tails}") from exc
