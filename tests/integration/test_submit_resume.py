"""``hoi-refine submit`` against a real server: interrupted half-way, re-run, everything exactly once.

The FastAPI app runs under uvicorn in a thread on 127.0.0.1 over a migrated SQLite file; two in-test
workers (``tests.support.live_server.LiveDeployment``) complete the jobs with a real
raw replay in MuJoCo (``worker.simulation.replay``). The per-key active-job limit is set to 2, so the tool also meets
real 429 answers with ``Retry-After`` and has to wait them out.
"""

from __future__ import annotations

import argparse
import io
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rich.console import Console

from common.api_client import ApiClient
from common.errors import InputError
from common.job_options import JobOptions
from common.result_format import read_arrays, read_summary
from common.sequence_io import save_sequence, sequence_from_npz_bytes
from common.settings import Settings
from service.submit import cli as submit_cli
from service.submit.manifest import Manifest
from service.submit.runner import SubmitConfig, SubmitOutcome, run_submit
from tests.support.live_server import LiveDeployment
from tests.support.queue_fixtures import tiny_sequence
from worker.simulation.replay import raw_replay, replay_result_bytes, replay_summary

SEQUENCES = 6


def replay_job(payload: bytes, options: JobOptions, progress: Any, should_stop: Any) -> tuple[bytes, dict[str, Any]]:
    """A worker job that simulates: the raw replay of the submitted sequence (no optimisation).

    A sequence named ``refuse-*`` fails the way a deterministic input problem does (not retried), so the
    tool's handling of FAILED jobs can be seen end to end.
    """
    seq = sequence_from_npz_bytes(payload)
    if seq.name.startswith("refuse-"):
        raise InputError(f"{seq.name}: refused by the test worker")
    result = raw_replay(seq)
    return replay_result_bytes(result), replay_summary(result)


class Deployment(LiveDeployment):
    """API server + two workers over one database, and the count of 429 answers the tool met."""

    def __init__(self, db_url: str) -> None:
        super().__init__(Settings(database_url=db_url, max_active_jobs_per_key=2, active_jobs_retry_after_seconds=1,
                                  poll_retry_after_seconds=1, lease_seconds=30.0), replay_job)  # fmt: skip
        self.throttled = 0


@pytest.fixture
def deployment(db_url: str) -> Iterator[Deployment]:
    dep = Deployment(db_url)
    dep.start_workers(2)
    try:
        yield dep
    finally:
        dep.stop()


def _dataset(folder: Path) -> None:
    """Six short sequences (NPZ and JSON, nested) and one invalid file that must never be sent."""
    for i in range(SEQUENCES):
        path = folder / "json" / f"part{i}" / f"s{i}.json" if i % 3 == 0 else folder / "npz" / f"s{i}.npz"
        path.parent.mkdir(parents=True, exist_ok=True)
        save_sequence(tiny_sequence(seed=i, frames=6, name=f"tiny-{i}"), path)
    (folder / "broken.json").write_text(json.dumps({"fps": 30, "object": {"mass_kg": 1}, "hands": []}))


def _run(dep: Deployment, data: Path, out: Path, console: Console, **kw: Any) -> SubmitOutcome:
    cfg = SubmitConfig(paths=[data], api_url=dep.url, api_key=dep.key, out_dir=out, wait=True, concurrency=3,
                       poll_interval_s=0.2, options=JobOptions(seed=1))  # fmt: skip
    with ApiClient(dep.url, dep.key) as client:
        outcome = run_submit(cfg, console=console, client=client, **kw)
    dep.throttled += client.throttled
    return outcome


def test_interrupt_and_resume_submits_each_sequence_once(
    deployment: Deployment, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data, out = tmp_path / "data", tmp_path / "out"
    _dataset(data)
    first_log = io.StringIO()

    submitted: list[str] = []

    def ctrl_c_half_way(event: str, entry: Any) -> None:
        if event == "submitted":
            submitted.append(entry.label)
            if len(submitted) == SEQUENCES // 2:
                raise KeyboardInterrupt  # what Ctrl-C does in the main thread

    first = _run(deployment, data, out, Console(file=first_log, width=300), on_event=ctrl_c_half_way)
    assert first.interrupted and first.exit_code == 130
    assert "Run the same command again to resume" in first_log.getvalue()
    # The manifest names exactly the jobs the server holds: nothing was sent that was not recorded.
    manifest = {e.source: e for e in Manifest.load_or_create(out).snapshot()}
    recorded = {e.job_id for e in manifest.values() if e.job_id}
    assert {j.id for j in deployment.jobs()} == recorded
    assert SEQUENCES // 2 <= len(recorded) < SEQUENCES

    second_log = io.StringIO()
    second = _run(deployment, data, out, Console(file=second_log, width=300))
    assert not second.interrupted
    assert second.exit_code == 1  # the broken file
    by_label = {e.label: e for e in second.entries}
    assert by_label["broken"].state == "INVALID" and "object_pose" in (by_label["broken"].error or "")

    # Each sequence was submitted once in total: one job each, one POST each, across both runs.
    jobs = deployment.jobs()
    assert len(jobs) == SEQUENCES
    assert sorted(j.name for j in jobs) == [f"tiny-{i}" for i in range(SEQUENCES)]
    assert all(j.state == "SUCCEEDED" for j in jobs), (jobs, second_log.getvalue())
    good = [e for e in second.entries if e.label != "broken"]
    assert sum(e.posts for e in good) == SEQUENCES
    assert {e.key for e in good} == {j.idempotency_key for j in jobs}

    # Every result and its contacts were downloaded, and they agree with each other.
    for e in good:
        blob = (out / e.files["result"]).read_bytes()
        summary = read_summary(blob)
        assert summary["kind"] == "replay" and e.metrics == summary["metrics"]
        contacts = json.loads((out / e.files["contacts"]).read_text())
        assert contacts["count"] == len(read_arrays(blob)["contact_frame"]) == len(contacts["contacts"])
    means = np.mean([e.metrics["raw"]["E_t"] for e in good if e.metrics])
    text = second_log.getvalue()
    assert "Jobs by state" in text and "SUCCEEDED" in text and f"{means:.2f}" in text
    assert "broken" in text and "INVALID" in text
    doc = json.loads((out / "summary.json").read_text())
    assert doc["states"] == {"INVALID": 1, "SUCCEEDED": SEQUENCES}
    assert doc["mean_metrics"]["raw"]["E_t"] == pytest.approx(means)

    # Both runs submitted into one server-side batch (its id kept in the manifest), printed at the end.
    batch_id = Manifest.load_or_create(out).meta["batch_id"]
    assert {j.batch_id for j in jobs} == {batch_id}
    assert f"batch: {deployment.url}/v1/batches/{batch_id}" in text.replace("\n", "")
    assert doc["batch"]["id"] == batch_id and doc["batch"]["counts"]["SUCCEEDED"] == SEQUENCES
    assert doc["batch"]["metrics"]["all_frames"]["raw"]["E_t"] == pytest.approx(means)
    assert "Batch metrics (all_frames)" in text

    # The per-key limit of 2 active jobs made the server answer 429 + Retry-After; the tool waited it out.
    assert deployment.throttled > 0

    # A third run, through the command line, finds nothing to do and sends nothing.
    parser = argparse.ArgumentParser()
    submit_cli.register(parser.add_subparsers())
    args = parser.parse_args(["submit", str(data), "--api", deployment.url, "--key", deployment.key, "--out",
                              str(out), "--wait", "--seed", "1", "--poll-interval", "0.2"])  # fmt: skip
    assert args.func(args) == 1
    assert "6 already done, 1 to check and submit" in capsys.readouterr().err
    assert len(deployment.jobs()) == SEQUENCES
    assert sum(e.posts for e in Manifest.load_or_create(out).snapshot()) == SEQUENCES

    # A job the server no longer knows (deleted) whose files are gone is submitted again, once.
    lost = good[0]
    with ApiClient(deployment.url, deployment.key) as client:
        client.request("DELETE", f"/v1/jobs/{lost.job_id}")
    (out / lost.files["result"]).unlink()
    fourth = _run(deployment, data, out, Console(file=io.StringIO(), width=300))
    again = {e.label: e for e in fourth.entries}[lost.label]
    assert again.state == "SUCCEEDED" and again.job_id != lost.job_id and again.posts == 1
    assert (out / again.files["result"]).is_file() and len(deployment.jobs()) == SEQUENCES


def test_without_wait_then_with_wait_and_a_failed_job(deployment: Deployment, tmp_path: Path) -> None:
    data, out = tmp_path / "data", tmp_path / "out"
    data.mkdir()
    for i, name in enumerate(("tiny-a", "tiny-b", "refuse-c")):
        save_sequence(tiny_sequence(seed=10 + i, frames=5, name=name), data / f"{name}.npz")
    two = [data / "tiny-a.npz", data / "tiny-b.npz"]
    cfg = SubmitConfig(paths=two, api_url=deployment.url, api_key=deployment.key, out_dir=out, wait=False,
                       poll_interval_s=0.2)  # fmt: skip
    submitted = run_submit(cfg, console=Console(file=io.StringIO(), width=300))
    assert submitted.exit_code == 0 and submitted.counts["submitted"] == 2
    assert not (out / "results").exists()  # nothing is downloaded without --wait

    # Now the whole folder, waiting: the two are tracked (not sent again), the third is sent and fails.
    log = io.StringIO()
    cfg.paths, cfg.wait = [data], True
    waited = run_submit(cfg, console=Console(file=log, width=300))
    states = {e.label: e.state for e in waited.entries}
    assert states == {"tiny-a": "SUCCEEDED", "tiny-b": "SUCCEEDED", "refuse-c": "FAILED"}
    assert waited.exit_code == 1
    failed = next(e for e in waited.entries if e.label == "refuse-c")
    assert "refused by the test worker" in (failed.error or "") and not failed.files
    assert "refused by the test worker" in log.getvalue()
    assert sum(e.posts for e in waited.entries) == 3 and len(deployment.jobs()) == 3
