"""Bulk submission: discover, validate, submit, track and download, resumable through the manifest.

Two bounded thread pools share one HTTP client: one prepares and submits (load + validate + pack + POST),
the other polls jobs and, with ``wait``, downloads results and contacts as soon as each job succeeds, so
downloads start while later sequences are still being submitted. Worker threads record every change in the
manifest themselves (atomic save under a lock); the main thread only schedules, draws progress and turns
Ctrl-C into a clean stop: no new work starts, requests in flight finish and are recorded, retries' waits
end at once, and the user is told to run the same command again. With ``retry_failed`` a job found FAILED is
requeued once per run (``POST /v1/jobs/{id}:retry``, same job id) instead of being reported as failed.

While it waits the main thread sleeps until the next poll is due (or a request finishes): it never spins. SIGINT
and SIGTERM stop the run cleanly (the run's own handler, so also where a shell started it with SIGINT ignored); a
second one aborts at once. Without a terminal a progress line is printed every ``progress_every_s`` seconds
instead of the bar. At the end the batch's report URLs are printed and its CSV and Parquet saved beside the
manifest.
"""

from __future__ import annotations

import hashlib
import json
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console

from common.api_client import ApiClient, Stopped, options_key_json
from common.errors import ApiError, HoiRefineError
from common.job_options import JobOptions
from common.job_state import FINISHED, JobState
from common.result_format import content_digest, read_summary
from common.stop_signals import stop_on_signals
from service.submit.batch import ensure_batch, print_batch, save_reports
from service.submit.discovery import Source, SourceFormat, discover, load_source
from service.submit.manifest import (
    FAILED_STATES,
    INVALID,
    NOT_SENT,
    REJECTED,
    UNSUCCESSFUL,
    Entry,
    Manifest,
    write_atomic,
)
from service.submit.payload import idempotency_key, sequence_payload
from service.submit.report import (
    ProgressLines,
    counts,
    describe,
    job_error,
    job_metrics,
    job_outcome,
    make_progress,
    print_summary,
    summary_document,
)

RESULTS_DIR = "results"
#: Machine-readable form of the closing summary, rewritten at the end of every run.
SUMMARY_NAME = "summary.json"
EXIT_OK, EXIT_FAILED, EXIT_INTERRUPTED = 0, 1, 130
#: Status requests per second over all tracked jobs, at most (each job's pause grows with their number).
MAX_POLLS_PER_S = 20.0
#: Longest sleep of the main thread between two looks at the run (stop flag, progress).
MAX_IDLE_S = 1.0

#: Called in the main thread after each step: ``(event, entry)`` with event one of submitted, invalid, rejected,
#: unreachable, error, lost (404: sent again), state, downloaded, retried. Tests use it to interrupt a run.
EventHook = Callable[[str, Entry], None]


@dataclass
class SubmitConfig:
    paths: list[Path]
    api_url: str
    api_key: str
    out_dir: Path
    options: JobOptions = field(default_factory=JobOptions)
    fmt: SourceFormat = "auto"
    concurrency: int = 4
    wait: bool = False
    #: Longest pause between two polls of one job (the server's ``Retry-After`` may shorten it).
    poll_interval_s: float = 2.0
    max_frames: int | None = None
    #: Requeue jobs that ended FAILED (once per run) rather than reporting them as failed.
    retry_failed: bool = False
    #: Seconds between two progress lines when the output is not a terminal (no bar can be drawn there).
    progress_every_s: float = 30.0


@dataclass
class SubmitOutcome:
    entries: list[Entry]
    interrupted: bool
    exit_code: int
    counts: dict[str, int]
    #: FAILED jobs this run requeued (``retry_failed``).
    retried: int = 0


def _fingerprint(src: Source, options: JobOptions) -> str:
    """Cheap change detector (sizes + mtimes + options) so a re-run need not re-read unchanged inputs."""
    files = [src.path] if src.path.is_file() else sorted(p for p in src.path.iterdir() if p.is_file())
    h = hashlib.sha256(options_key_json(options).encode())
    for f in files:
        st = f.stat()
        h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()[:32]


class _Run:
    def __init__(self, cfg: SubmitConfig, client: ApiClient, manifest: Manifest, stop: threading.Event) -> None:
        self.cfg, self.client, self.manifest, self.stop = cfg, client, manifest, stop
        #: The run's batch on the server (``service.submit.batch``); None for a server without batches.
        self.batch_id: str | None = None
        self.results_dir = cfg.out_dir / RESULTS_DIR
        #: Why the run stopped early, when the service kept failing after all retries.
        self.unreachable: str | None = None

    def give_up(self, why: str) -> None:
        """Retries are spent: the service is down or broken. Going on would spend the same minutes of backoff
        on every remaining sequence, so stop here (in the worker thread, before it takes the next task)."""
        self.unreachable = self.unreachable or why
        self.stop.set()

    # ------------------------------------------------------------------ submit side (worker threads)
    def prepare_and_submit(self, entry: Entry, src: Source) -> str:
        fp = _fingerprint(src, self.cfg.options)
        try:
            seq = load_source(src, max_frames=self.cfg.max_frames)
            payload = sequence_payload(seq, max_frames=self.cfg.max_frames)
        except HoiRefineError as exc:
            self.manifest.update(entry, state=INVALID, error=str(exc), job_id=None, key=None)
            return "invalid"
        key = idempotency_key(payload, self.cfg.options)
        if entry.job_id is not None and entry.key == key and entry.state not in NOT_SENT:
            self.manifest.update(entry, fingerprint=fp)  # unchanged since it was submitted: just track it
            return "state"
        if entry.key != key or entry.state in NOT_SENT:
            self.manifest.reset(entry, key)
        self.manifest.update(entry, key=key, sequence=seq.name)
        if self.stop.is_set():
            return "stopped"
        try:
            doc = self.client.submit(payload, f"{src.label}.npz", self.cfg.options, key, self.batch_id)
        except ApiError as exc:
            if exc.status is not None and 400 <= exc.status < 500:
                self.manifest.update(entry, state=REJECTED, error=str(exc), posts=entry.posts + 1)
                return "rejected"
            self.manifest.update(entry, error=str(exc), posts=entry.posts + 1)  # stays PENDING: re-run retries
            self.give_up(str(exc))
            return "unreachable"
        self.manifest.update(
            entry,
            job_id=doc["id"],
            state=str(doc.get("state") or JobState.QUEUED),
            attempt=doc.get("attempt"),
            error=None,
            posts=entry.posts + 1,
            fingerprint=fp,
        )
        return "submitted"

    # ------------------------------------------------------------------ tracking side (worker threads)
    def poll(self, entry: Entry, download: bool) -> tuple[str, float | None]:
        assert entry.job_id is not None
        try:
            doc, hint = self.client.job(entry.job_id)
        except ApiError as exc:
            if exc.status is None or exc.status >= 500:
                self.give_up(str(exc))
            if exc.status != 404 or entry.key is None:
                raise
            # The server does not know the job (deleted, or another deployment): forget it and submit again;
            # the Idempotency-Key still guards against a duplicate if the job exists under another id.
            self.manifest.reset(entry, entry.key)
            return "lost", None
        state = str(doc.get("state", entry.state))
        error = job_error(doc) if state in UNSUCCESSFUL else None
        metrics = job_metrics(doc) or entry.metrics
        outcome, reason = job_outcome(doc)
        self.manifest.update(entry, state=state, attempt=doc.get("attempt", entry.attempt), error=error,
                             metrics=metrics, outcome=outcome, reason=reason)  # fmt: skip
        if state == JobState.SUCCEEDED and download:
            try:
                self.download(entry)
            except ApiError as exc:
                if exc.status is None or exc.status >= 500:
                    self.give_up(str(exc))
                raise
            return "downloaded", hint
        return "state", hint

    def retry(self, entry: Entry) -> str:
        """Requeue the entry's FAILED job under its id; the manifest counts it in ``retries``."""
        assert entry.job_id is not None
        try:
            doc = self.client.retry_job(entry.job_id)
        except ApiError as exc:
            if exc.status is None or exc.status >= 500:
                self.give_up(str(exc))
            if exc.status == 404 and entry.key is not None:
                self.manifest.reset(entry, entry.key)  # the server forgot the job: submit it again
                return "lost"
            if exc.status != 409:
                raise
            # No longer FAILED (requeued by someone else, or an earlier answer of ours was lost): track it.
            doc, _ = self.client.job(entry.job_id)
            self.manifest.update(entry, state=str(doc.get("state", entry.state)), attempt=doc.get("attempt"))
            return "state"
        state = str(doc.get("state") or JobState.QUEUED)
        self.manifest.update(entry, state=state, attempt=doc.get("attempt"), error=None, retries=entry.retries + 1)
        return "retried"

    def download(self, entry: Entry) -> None:
        assert entry.job_id is not None
        self.results_dir.mkdir(parents=True, exist_ok=True)
        result_rel = f"{RESULTS_DIR}/{entry.label}.result.npz"
        contacts_rel = f"{RESULTS_DIR}/{entry.label}.contacts.json"
        blob = self.client.result(entry.job_id)
        summary = read_summary(blob)  # also proves the file is a readable result before it is kept
        write_atomic(self.cfg.out_dir / result_rel, blob)
        metrics = dict(summary.get("metrics") or entry.metrics or {})
        proof = (entry.metrics or {}).get("verification")
        if isinstance(proof, dict):
            # The worker's verification travels with the dataset, with whether this copy is the file it checked
            # (``hoi-refine verify`` on the file prints the same content sha256).
            metrics["verification"] = {**proof, "download_matches": content_digest(blob) == proof.get("content_sha256")}
        self.manifest.update(entry, files={**entry.files, "result": result_rel}, metrics=metrics)
        contacts = self.client.contacts(entry.job_id)
        write_atomic(self.cfg.out_dir / contacts_rel, json.dumps(contacts).encode())
        self.manifest.update(entry, files={**entry.files, "contacts": contacts_rel})

    def downloaded(self, entry: Entry) -> bool:
        """Succeeded, and its result and contacts are on disk (nothing left to do for it)."""
        return (
            entry.state == JobState.SUCCEEDED
            and {"result", "contacts"} <= entry.files.keys()
            and all((self.cfg.out_dir / p).is_file() for p in entry.files.values())
        )


def run_submit(
    cfg: SubmitConfig,
    *,
    client: ApiClient | None = None,
    console: Console | None = None,
    stop: threading.Event | None = None,
    on_event: EventHook | None = None,
) -> SubmitOutcome:
    """Submit every sequence under ``cfg.paths``; with ``cfg.wait`` also wait and download. Resumable."""
    console = console or Console(stderr=True)
    stop = stop or threading.Event()
    cfg.out_dir.mkdir(parents=True, exist_ok=True)
    manifest = Manifest.load_or_create(cfg.out_dir)
    opts = json.loads(options_key_json(cfg.options))
    if manifest.meta.get("options") not in (None, opts):
        console.print("[yellow]options differ from the manifest's: changed inputs get new jobs[/yellow]")
    if manifest.meta.get("api") not in (None, cfg.api_url):
        console.print(
            f"[yellow]the manifest was written for {manifest.meta['api']}; jobs that {cfg.api_url} does not know "
            "are submitted again[/yellow]",
            highlight=False,
        )
    manifest.meta.update({"api": cfg.api_url, "options": opts, "format": cfg.fmt})
    sources = discover(cfg.paths, cfg.fmt, exclude=[cfg.out_dir])
    entries = [(manifest.get_or_add(s.ident, s.label, s.kind), s) for s in sources]
    manifest.save()
    own_client = client is None
    client = client or ApiClient(
        cfg.api_url, cfg.api_key, stop=stop, pool_size=2 * cfg.concurrency, user_agent="hoi-refine-submit/1"
    )
    client.stop = stop
    run = _Run(cfg, client, manifest, stop)
    try:
        run.batch_id = ensure_batch(client, manifest, cfg.api_url, cfg.out_dir.resolve().name, console)
    except ApiError as exc:  # the service is down: nothing can be submitted now
        run.give_up(str(exc))

    fp_cache = {e.source: _fingerprint(s, cfg.options) for e, s in entries}
    to_submit = [
        (e, s) for e, s in entries
        if not (e.job_id and e.state not in NOT_SENT and e.fingerprint == fp_cache[e.source])
        and not run.downloaded(e)
    ]  # fmt: skip
    submitting = {e.source for e, _ in to_submit}
    visible = [e for e, _ in entries]
    retryable = [e for e in visible if e.state == JobState.FAILED and e.source not in submitting]
    to_retry = len(retryable) if cfg.retry_failed else 0
    retrying = f"{to_retry} FAILED to retry, " if to_retry else ""
    console.print(
        f"{len(entries)} sequences: {sum(run.downloaded(e) for e in visible)} already done, "
        f"{len(to_submit)} to check and submit, {retrying}out: {cfg.out_dir}",
        highlight=False,
    )

    interrupted = False
    polls_due: dict[str, float] = {}
    polled_once: set[str] = set()
    gave_up: set[str] = set()  # polling/downloading failed after retries: left for the next run
    resubmitted: set[str] = set()  # jobs the server no longer knew (404), sent again once
    retry_asked: set[str] = set()  # FAILED jobs sent to :retry this run (once each: a job failing again stays failed)
    retried: set[str] = set()  # ... and requeued by it
    source_of = {e.source: s for e, s in entries}
    futures: dict[Future[Any], tuple[str, Entry]] = {}
    submit_pool = ThreadPoolExecutor(max_workers=cfg.concurrency, thread_name_prefix="submit")
    poll_pool = ThreadPoolExecutor(max_workers=cfg.concurrency, thread_name_prefix="poll")

    def needs_tracking(e: Entry) -> bool:
        if e.job_id is None or e.source in submitting or e.source in gave_up:
            return False
        if cfg.wait:
            return not run.downloaded(e) and e.state not in UNSUCCESSFUL
        return e.source not in polled_once and e.state not in FINISHED

    def finished_count() -> int:
        if cfg.wait:
            return sum(run.downloaded(e) or e.state in FAILED_STATES for e in visible)
        return sum(e.job_id is not None or e.state in FAILED_STATES for e in visible)

    def idle_for(tracked: list[Entry], in_flight: set[str], now: float) -> float:
        """How long the main thread may sleep: until the next poll is due, at most ``MAX_IDLE_S``."""
        due = [polls_due.get(e.source, 0.0) for e in tracked if e.source not in in_flight]
        pause = min([MAX_IDLE_S, *(d - now for d in due)])
        if lines is not None:
            pause = min(pause, lines.seconds_to_next())
        return max(pause, 0.0)

    progress = make_progress(console)
    lines = None if console.is_terminal else ProgressLines(console, cfg.progress_every_s, len(visible))
    try:
        with progress if lines is None else _nothing(), _stop_on_signals(stop, console):
            bar = progress.add_task(describe(visible), total=len(visible), completed=finished_count())
            for e, s in to_submit:
                futures[submit_pool.submit(run.prepare_and_submit, e, s)] = ("submit", e)
            while True:
                if stop.is_set():
                    interrupted = run.unreachable is None
                    break
                now = time.monotonic()
                if cfg.retry_failed:
                    busy = {e.source for _, e in futures.values()}
                    for e in visible:
                        if e.state == JobState.FAILED and e.job_id and e.source not in retry_asked | busy | submitting:
                            retry_asked.add(e.source)
                            futures[poll_pool.submit(run.retry, e)] = ("retry", e)
                in_flight = {e.source for kind, e in futures.values() if kind == "poll"}
                tracked = [e for e in visible if needs_tracking(e)]
                for e in tracked:
                    if e.source not in in_flight and polls_due.get(e.source, 0.0) <= now:
                        polls_due[e.source] = float("inf")
                        futures[poll_pool.submit(run.poll, e, cfg.wait)] = ("poll", e)
                if not futures and not tracked:
                    break
                # ``wait`` on no futures returns at once: sleep on the stop flag instead (Ctrl-C ends it).
                pause = idle_for(tracked, in_flight | {e.source for _, e in futures.values()}, now)
                if futures:
                    done, _ = wait(list(futures), timeout=pause, return_when=FIRST_COMPLETED)
                else:
                    stop.wait(pause)
                    done = set()
                for fut in done:
                    kind, e = futures.pop(fut)
                    event = _settle(fut, kind, e, manifest, console)
                    if kind == "submit":
                        submitting.discard(e.source)
                        polls_due[e.source] = time.monotonic() + min(0.5, cfg.poll_interval_s)
                    elif event == "lost" and e.source not in resubmitted:
                        resubmitted.add(e.source)
                        submitting.add(e.source)
                        futures[submit_pool.submit(run.prepare_and_submit, e, source_of[e.source])] = ("submit", e)
                    elif event in ("error", "lost", "unreachable"):
                        gave_up.add(e.source)
                    elif kind == "retry":
                        if event == "retried":
                            retried.add(e.source)
                        polled_once.discard(e.source)  # track the requeued job (without --wait: one look)
                        polls_due[e.source] = time.monotonic() + min(0.5, cfg.poll_interval_s)
                    else:
                        polled_once.add(e.source)
                        hint = fut.result()[1] if event in ("state", "downloaded") else None
                        delay = cfg.poll_interval_s if hint is None else min(max(hint, 0.05), cfg.poll_interval_s)
                        # Thousands of queued jobs must not turn into thousands of requests a second.
                        delay = max(delay, len(tracked) / MAX_POLLS_PER_S)
                        polls_due[e.source] = time.monotonic() + delay
                    if on_event is not None and event != "stopped":
                        on_event(event, e)
                progress.update(bar, description=describe(visible), completed=finished_count())
                if lines is not None:
                    lines.update(visible, finished_count())
    except KeyboardInterrupt:
        interrupted = True
    finally:
        stop.set()  # ends every retry wait; requests in flight complete and are recorded
        submit_pool.shutdown(wait=True, cancel_futures=True)
        poll_pool.shutdown(wait=True, cancel_futures=True)
        manifest.save()

    if lines is not None:
        lines.update(visible, finished_count(), force=True)
    print_summary(console, visible, retried=len(retried), retry_hint=not cfg.retry_failed)
    document = summary_document(visible, len(retried))
    if run.batch_id is not None and run.unreachable is None:
        client.stop = threading.Event()  # the run's stop is set by now; these last reads may go out
        document["batch"] = print_batch(console, client, cfg.api_url, run.batch_id)
        if not interrupted:
            document["reports"] = save_reports(console, client, cfg.api_url, run.batch_id, cfg.out_dir)
    if own_client:
        client.close()
    write_atomic(cfg.out_dir / SUMMARY_NAME, json.dumps(document, indent=1).encode())
    if run.unreachable is not None:
        console.print(
            f"[red]Stopped: the service keeps failing[/red] ({run.unreachable}). The manifest ({manifest.path}) is up "
            "to date; run the same command again when the service is back.",
            highlight=False,
        )
    if interrupted:
        console.print(
            f"[yellow]Interrupted.[/yellow] {finished_count()} of {len(visible)} finished; the manifest "
            f"({manifest.path}) is up to date. Run the same command again to resume.",
            highlight=False,
        )
    if cfg.wait:
        failed = any(not run.downloaded(e) for e in visible)
    else:
        failed = any(e.state in FAILED_STATES or e.job_id is None for e in visible)
    code = EXIT_INTERRUPTED if interrupted else EXIT_FAILED if failed else EXIT_OK
    return SubmitOutcome(entries=visible, interrupted=interrupted, exit_code=code, counts=counts(visible),
                         retried=len(retried))  # fmt: skip


@contextmanager
def _nothing() -> Iterator[None]:
    yield


def _stop_on_signals(stop: threading.Event, console: Console) -> AbstractContextManager[None]:
    """SIGINT / SIGTERM set ``stop`` (the run winds down and says how to resume); a second one aborts. No
    KeyboardInterrupt lands in the middle of a manifest update (``common.stop_signals``)."""

    def say(sig: signal.Signals, again: bool) -> None:
        if again:
            raise KeyboardInterrupt
        console.print(f"\n{sig.name}: stopping (requests in flight finish; again to abort)", highlight=False)

    return stop_on_signals(stop, say)


def _settle(fut: Future[Any], kind: str, entry: Entry, manifest: Manifest, console: Console) -> str:
    """The event a finished task stands for; unexpected errors are recorded on the entry, not raised."""
    try:
        result = fut.result()
    except Stopped:
        return "stopped"
    except ApiError as exc:  # retries exhausted while polling/downloading: try again on the next run
        manifest.update(entry, error=str(exc))
        console.print(f"[red]error[/red] {entry.label}: {exc}", highlight=False)
        return "error" if exc.status is not None and 400 <= exc.status < 500 else "unreachable"
    except (HoiRefineError, OSError, ValueError) as exc:
        manifest.update(entry, error=f"{type(exc).__name__}: {exc}")
        console.print(f"[red]error[/red] {entry.label}: {exc}", highlight=False)
        return "error"
    if kind in ("submit", "retry"):
        assert isinstance(result, str)
        if result in ("invalid", "rejected", "unreachable"):
            console.print(f"[red]{result}[/red] {entry.label}: {entry.error}", highlight=False)
        return result
    return str(result[0])
