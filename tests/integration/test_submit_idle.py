"""``hoi-refine submit --wait`` as a user runs it (a process of its own, output to a pipe), against a real server
(issue #53 item 8): while its jobs wait in the queue it idles (the CPU seconds it spends are counted with
psutil: well under 5 % of a core), it prints a progress line every so often, SIGINT stops it cleanly (also when
it was started with SIGINT ignored, as a shell's background job is), and the same command resumes the batch:
nothing is submitted twice, results come down, the outcome is summarised first and the batch's report is saved
as CSV and Parquet beside the manifest (item 6).
"""

from __future__ import annotations

import csv
import io
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psutil
import pyarrow.parquet as pq
import pytest

from common.job_options import JobOptions
from common.sequence_io import save_sequence, sequence_from_npz_bytes
from common.settings import Settings
from tests.support.live_server import LiveDeployment
from tests.support.queue_fixtures import tiny_sequence
from worker.simulation.replay import raw_replay, replay_result_bytes, replay_summary

SEQUENCES = 3
#: How long the CPU of the waiting client is counted over, and the share of one core it may use.
WINDOW_S = 4.0
MAX_CPU_SHARE = 0.05
REASON = {"code": "no_contact", "frame": 2, "value": 3.5, "unit": "cm",
          "message": "the simulated hand never touches the object (closest 3.5 cm at frame 2)"}  # fmt: skip


def replay_job(payload: bytes, options: JobOptions, progress: Any, should_stop: Any) -> tuple[bytes, dict[str, Any]]:
    """The raw replay of the sequence, with an outcome as the refinement gives one: ``tiny-1`` is not executable."""
    seq = sequence_from_npz_bytes(payload)
    result = raw_replay(seq)
    summary = replay_summary(result)
    executable = seq.name != "tiny-1"
    summary["outcome"] = {"executable": executable, "protocol": "paper", "reasons": [] if executable else [REASON]}
    return replay_result_bytes(result), summary


@pytest.fixture
def server(db_url: str) -> Iterator[LiveDeployment]:
    """The API over a migrated SQLite file; its worker starts only once the test says so."""
    srv = LiveDeployment(Settings(database_url=db_url, poll_retry_after_seconds=1, lease_seconds=30.0), replay_job)
    try:
        yield srv
    finally:
        srv.stop()


def submit_command(srv: LiveDeployment, data: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "common.cli", "submit", str(data), "--api", srv.url, "--key", srv.key, "--out",
            str(out), "--wait", "--poll-interval", "0.5", "--progress-every", "0.5", "--seed", "2"]  # fmt: skip


def wait_for(predicate: Any, what: str, proc: subprocess.Popen[bytes], timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert proc.poll() is None, f"submit exited ({proc.returncode}) before {what}"
        assert time.monotonic() < deadline, f"no {what} within {timeout_s:.0f} s"
        time.sleep(0.2)


def all_submitted(out: Path) -> bool:
    try:
        entries = json.loads((out / "manifest.json").read_text())["entries"]
    except (OSError, ValueError, KeyError):
        return False
    return len(entries) == SEQUENCES and all(e.get("job_id") for e in entries)


@pytest.mark.parametrize("sigint_ignored", [False, True], ids=["sigint", "sigint-ignored-at-start"])
@pytest.mark.parametrize("empty_db_url", ["sqlite"], indirect=True)
def test_a_waiting_submit_idles_prints_progress_stops_on_sigint_and_resumes(
    server: LiveDeployment, tmp_path: Path, sigint_ignored: bool
) -> None:
    data, out = tmp_path / "data", tmp_path / "out"
    data.mkdir()
    for i in range(SEQUENCES):
        save_sequence(tiny_sequence(seed=i, frames=6, name=f"tiny-{i}"), data / f"s{i}.npz")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}

    def ignore_sigint() -> None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    log = tmp_path / "first.log"
    with log.open("wb") as sink:
        proc = subprocess.Popen(submit_command(server, data, out), stdout=sink, stderr=subprocess.STDOUT, env=env,
                                preexec_fn=ignore_sigint if sigint_ignored else None)  # fmt: skip
        try:
            wait_for(lambda: all_submitted(out), "every sequence submitted", proc)
            # No worker runs: the client has nothing to do but poll. Count the CPU seconds it spends.
            client = psutil.Process(proc.pid)
            before, started = client.cpu_times(), time.monotonic()
            time.sleep(WINDOW_S)
            after, window = client.cpu_times(), time.monotonic() - started
            cpu_s = (after.user + after.system) - (before.user + before.system)
            assert cpu_s < MAX_CPU_SHARE * window, f"{cpu_s:.2f} CPU s over {window:.1f} s while waiting"
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=60) == 130
        finally:
            if proc.poll() is None:
                proc.kill()
    text = log.read_text()
    assert "SIGINT: stopping" in text and "Run the same command again to resume" in text
    # A progress line every half second of the wait (no terminal: no bar).
    lines = [ln for ln in text.splitlines() if f"/{SEQUENCES} finished: submitted {SEQUENCES}" in ln]
    assert len(lines) >= 3, text
    jobs = server.jobs()
    assert len(jobs) == SEQUENCES and {j.state for j in jobs} == {"QUEUED"}

    # The same command resumes: the same jobs (none sent again) run and come down.
    server.start_workers()
    done = subprocess.run(submit_command(server, data, out), capture_output=True, env=env, timeout=300)
    text = done.stdout.decode() + done.stderr.decode()
    assert done.returncode == 0, text
    assert {j.id for j in server.jobs()} == {j.id for j in jobs} and len({j.batch_id for j in jobs}) == 1
    assert f"{SEQUENCES} sequences: 0 already done" in text
    # The outcome comes first, with the reason of the one that is not executable.
    flat = " ".join(text.split())
    assert flat.index("Outcome of 3 succeeded sequences") < flat.index("Jobs by state")
    assert "not executable s1: no_contact: the simulated hand never touches the object" in flat, flat
    batch_id = jobs[0].batch_id
    for fmt in ("csv", "parquet"):
        assert f"report ({fmt}): {server.url}/v1/batches/{batch_id}/report?format={fmt}" in text
    rows = list(csv.DictReader(io.StringIO((out / "report.csv").read_text())))
    assert sorted((r["name"], r["outcome"], r["reason"]) for r in rows) == [
        ("tiny-0", "executable", ""), ("tiny-1", "not_executable", "no_contact"), ("tiny-2", "executable", "")]
    assert pq.read_table(out / "report.parquet").num_rows == SEQUENCES
    summary = json.loads((out / "summary.json").read_text())
    assert summary["outcomes"] == {"executable": 2, "not_executable": 1, "unknown": 0}
    assert summary["not_executable"][0]["reason"]["code"] == "no_contact"
    assert summary["reports"] == {"csv": str(out / "report.csv"), "parquet": str(out / "report.parquet")}
