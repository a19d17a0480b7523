"""``hoi-refine submit --retry-failed`` against the real FastAPI app, in-process (Starlette's test transport
under the tool's own ``ApiClient``; no server, no Ray): FAILED jobs are requeued under the same id, once
per run, the manifest and the summary count it, and without the flag nothing changes but a hint."""

from __future__ import annotations

import io
import json
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from rich.console import Console

from common.api_client import ApiClient, RetryPolicy
from common.database import create_engine_for
from common.queue import JobQueue
from common.sequence_io import save_sequence
from service.submit.manifest import Manifest
from service.submit.runner import SubmitConfig, SubmitOutcome, run_submit
from tests.support.queue_fixtures import ApiHarness, fake_result, tiny_sequence


def _dataset(folder: Path, names: list[str]) -> None:
    folder.mkdir()
    for i, name in enumerate(names):
        save_sequence(tiny_sequence(seed=20 + i, frames=5, name=name), folder / f"{name}.npz")


def _run(api: ApiHarness, data: Path, out: Path, **cfg_kw: object) -> tuple[SubmitOutcome, str]:
    key = api.headers["Authorization"].removeprefix("Bearer ")
    cfg = SubmitConfig(paths=[data], api_url="http://testserver", api_key=key, out_dir=out, concurrency=2,
                       poll_interval_s=0.05, **cfg_kw)  # type: ignore[arg-type]  # fmt: skip
    client = ApiClient("http://testserver", key, transport=api.client._transport,
                       retry=RetryPolicy(max_retries=1, backoff_base_s=0.001))  # fmt: skip
    log = io.StringIO()
    outcome = run_submit(cfg, client=client, console=Console(file=log, width=300))
    return outcome, log.getvalue()


def _fail_queued(queue: JobQueue) -> list[str]:
    """Play a worker whose every attempt fails (not retryable): each QUEUED job ends FAILED."""
    failed = []
    while (lease := queue.claim("w")) is not None:
        queue.fail(lease.job_id, lease.lease_token, f"boom in {lease.name}")
        failed.append(lease.job_id)
    return failed


def test_without_the_flag_failed_jobs_stay_failed_with_it_they_are_requeued_once(
    api: ApiHarness, tmp_path: Path
) -> None:
    data, out = tmp_path / "data", tmp_path / "out"
    _dataset(data, ["a", "b", "c"])
    first, _ = _run(api, data, out)
    assert first.exit_code == 0 and first.counts["submitted"] == 3
    a, b, c = (e.job_id for e in sorted(first.entries, key=lambda e: e.label))
    assert a and b and c
    api.queue.cancel(None, c)  # c is CANCELLED: --retry-failed leaves it alone (the API retries FAILED only)
    assert sorted(_fail_queued(api.queue)) == sorted([a, b])

    plain, log = _run(api, data, out)
    assert plain.exit_code == 1 and plain.retried == 0
    assert sorted(e.state for e in plain.entries) == ["CANCELLED", "FAILED", "FAILED"]
    assert "2 jobs FAILED on the service: run the same command with --retry-failed" in log
    assert {api.queue.get(None, j).state for j in (a, b)} == {"FAILED"}

    api.queue.retry(None, b)  # someone else requeues b meanwhile: the tool's :retry then meets a 409
    retried, log = _run(api, data, out, retry_failed=True)
    assert "2 FAILED to retry" in log and "retried 1 FAILED job (same job ids" in log
    assert retried.retried == 1 and retried.exit_code == 1  # c stays CANCELLED
    by_job = {e.job_id: e for e in retried.entries}
    assert (by_job[a].state, by_job[a].retries, by_job[a].error) == ("QUEUED", 1, None)
    assert (by_job[b].state, by_job[b].retries) == ("QUEUED", 0)  # requeued, but not by this tool
    assert api.queue.get(None, a).state == "QUEUED" and api.queue.get(None, a).attempt == 1
    assert [e.kind for e in api.queue.events(None, a)] == ["submitted", "claimed", "failed", "retried"]
    # Same jobs, no new POST: the manifest and the summary file record the retry.
    assert len(api.queue.list(None)[0]) == 3 and all(e.posts == 1 for e in retried.entries)
    saved = {e.job_id: e for e in Manifest.load_or_create(out).snapshot()}
    assert saved[a].retries == 1 and saved[a].state == "QUEUED"
    assert json.loads((out / "summary.json").read_text())["retried"] == 1

    # Nothing is FAILED now: a further run with the flag has nothing to retry.
    again, log = _run(api, data, out, retry_failed=True)
    assert again.retried == 0 and "to retry" not in log and "--retry-failed" not in log


@pytest.fixture
def flaky_worker(db_url: str) -> Iterator[JobQueue]:
    """A worker thread on its own engine: ``flaky-*`` fails its first attempt only, ``refuse-*`` every one,
    the rest succeed with a small fake result."""
    engine = create_engine_for(db_url)
    queue = JobQueue(engine)
    stop, seen = threading.Event(), set()

    def work() -> None:
        while not stop.is_set():
            lease = queue.claim("flaky-worker")
            if lease is None:
                stop.wait(0.02)
            elif lease.name.startswith("refuse") or (lease.name.startswith("flaky") and lease.job_id not in seen):
                seen.add(lease.job_id)
                queue.fail(lease.job_id, lease.lease_token, f"{lease.name} failed")
            else:
                queue.complete(lease.job_id, lease.lease_token, *fake_result())

    thread = threading.Thread(target=work, daemon=True)
    thread.start()
    try:
        yield queue
    finally:
        stop.set()
        thread.join(timeout=30)
        engine.dispose()


def test_with_wait_a_retried_job_is_followed_to_the_end_and_retried_only_once_per_run(
    api: ApiHarness, flaky_worker: JobQueue, tmp_path: Path
) -> None:
    data, out = tmp_path / "data", tmp_path / "out"
    _dataset(data, ["ok", "flaky", "refuse"])
    first, log = _run(api, data, out, wait=True)
    states = {e.label: e.state for e in first.entries}
    assert states == {"ok": "SUCCEEDED", "flaky": "FAILED", "refuse": "FAILED"} and first.exit_code == 1
    assert "--retry-failed" in log

    second, log = _run(api, data, out, wait=True, retry_failed=True)
    entries = {e.label: e for e in second.entries}
    assert entries["flaky"].state == "SUCCEEDED" and (out / entries["flaky"].files["result"]).is_file()
    # refuse failed again after its retry: reported, not retried a second time in the same run.
    assert entries["refuse"].state == "FAILED" and entries["refuse"].retries == 1
    assert second.retried == 2 and second.exit_code == 1 and "retried 2 FAILED jobs" in log
    kinds = [e.kind for e in flaky_worker.events(None, entries["refuse"].job_id or "")]
    assert kinds.count("retried") == 1 and kinds.count("failed") == 2
    assert entries["ok"].retries == 0 and all(e.posts == 1 for e in second.entries)


def test_the_flag_reaches_the_run(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import argparse

    from service.submit import cli, runner

    seen: list[SubmitConfig] = []

    def fake_run(cfg: SubmitConfig) -> SubmitOutcome:
        seen.append(cfg)
        return SubmitOutcome([], False, 0, {})

    monkeypatch.setattr(runner, "run_submit", fake_run)
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers())
    for extra, expected in (([], False), (["--retry-failed"], True)):
        args = parser.parse_args(["submit", str(tmp_path), "--api", "http://x", "--key", "k", *extra])
        assert args.func(args) == 0 and seen[-1].retry_failed is expected
