"""API and queue load benchmark: status-polling throughput/latency and claim throughput, SQLite and PostgreSQL.

1. Polling: a uvicorn subprocess on 127.0.0.1 serves the app; an open-loop client fires
   ``GET /v1/jobs/{id}`` at a fixed rate (default 200 req/s for 30 s) over a set of submitted jobs and records
   each latency, once plain and once as a caching client would (``If-None-Match`` with the last ETag); then
   a closed-loop run (``--concurrency`` clients back to back) finds the saturation rate. With
   ``--refine-workers N`` a ``hoi-refine worker --workers N`` process refines real sequences (the built-in
   example) on the same machine the whole time, as ``hoi-refine up`` does (issue #20).
2. Claims: ``--claim-jobs`` jobs are queued, then ``--claimers`` spawned processes claim + complete until the
   queue is empty (each job claimed exactly once is checked too).

    .venv/bin/python bench/api_load.py                          # both backends, results to stdout
    .venv/bin/python bench/api_load.py --out bench/results/api_load.md
    .venv/bin/python bench/api_load.py --refine-workers 2 --out bench/results/api_load.md

PostgreSQL uses ``HOI_REFINE_TEST_POSTGRES_URL`` (or ``--postgres-url``), in a scratch schema dropped after.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import httpx
import numpy as np
import sqlalchemy as sa

#: Connections the open-loop client spreads its requests over.
OPEN_LOOP_CONNECTIONS = 32
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # bench/ runs as a script; the claimer body lives in tests/support/queue_claimer.py

from common.api_client import wait_until_ready  # noqa: E402
from common.api_key_store import ApiKeyStore  # noqa: E402
from common.database import create_engine_for, upgrade_to_head  # noqa: E402
from common.errors import ApiError  # noqa: E402
from common.job_options import JobOptions  # noqa: E402
from common.queue import JobQueue  # noqa: E402
from common.sequence_io import sequence_to_json_dict, sequence_to_npz_bytes  # noqa: E402
from common.settings import Settings  # noqa: E402
from tests.support.queue_claimer import run_claimers  # noqa: E402
from tests.support.queue_fixtures import tiny_payload, tiny_sequence  # noqa: E402
from worker.example import example_sequence  # noqa: E402


@dataclass
class PollFigures:
    mode: str
    requests: int
    errors: int
    seconds: float
    p50_ms: float
    p99_ms: float
    #: uvicorn process CPU time per request: what a request costs, independent of other load on the machine.
    server_cpu_ms: float = float("nan")
    #: Jobs RUNNING (refined by the workers) when the run started and when it ended.
    running: str = "-"
    not_modified: int = 0

    @property
    def rate(self) -> float:
        return self.requests / self.seconds


@dataclass
class ClaimFigures:
    jobs: int
    claimers: int
    seconds: float
    duplicates: int


@contextmanager
def database(backend: str, postgres_url: str | None) -> Iterator[str]:
    if backend == "sqlite":
        with tempfile.TemporaryDirectory(prefix="hoi-bench-") as tmp:
            yield f"sqlite:///{Path(tmp) / 'bench.sqlite3'}"
        return
    if not postgres_url:
        raise SystemExit("PostgreSQL: set HOI_REFINE_TEST_POSTGRES_URL or pass --postgres-url")
    schema = f"hoi_bench_{uuid.uuid4().hex[:10]}"
    admin = sa.create_engine(postgres_url)
    with admin.begin() as conn:
        conn.exec_driver_sql(f"CREATE SCHEMA {schema}")
    sep = "&" if "?" in postgres_url else "?"
    try:
        yield f"{postgres_url}{sep}options=-csearch_path%3D{schema}"
    finally:
        with admin.begin() as conn:
            conn.exec_driver_sql(f"DROP SCHEMA {schema} CASCADE")
        admin.dispose()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def process_cpu_seconds(pid: int) -> float:
    """utime + stime of a process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@contextmanager
def server(url: str) -> Iterator[tuple[str, int]]:
    port = free_port()
    env = {**os.environ, "HOI_REFINE_DATABASE_URL": url, "HOI_REFINE_MAX_ACTIVE_JOBS_PER_KEY": "100000"}
    cmd = [sys.executable, "-m", "uvicorn", "--factory", "service.app:create_app", "--host", "127.0.0.1",
           "--port", str(port), "--log-level", "warning", "--no-access-log"]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env)
    base = f"http://127.0.0.1:{port}"
    try:
        try:
            wait_until_ready(base, 30, alive=lambda: proc.poll() is None, interval_s=0.2)
        except ApiError as exc:
            raise SystemExit(f"uvicorn did not become ready: {exc}") from exc
        yield base, proc.pid
    finally:
        proc.terminate()
        proc.wait(timeout=10)


class Connection:
    """One keep-alive HTTP/1.1 connection speaking just enough of the protocol for ``GET`` (a lean client:
    on two shared cores a general-purpose async client costs more CPU per request than the server does)."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, auth: bytes) -> None:
        self.reader, self.writer, self.auth = reader, writer, auth

    @classmethod
    async def open(cls, base: str, key: str) -> Connection:
        host, port = base.removeprefix("http://").split(":")
        reader, writer = await asyncio.open_connection(host, int(port))
        return cls(reader, writer, f"Authorization: Bearer {key}\r\n".encode())

    async def get(self, path: str, etags: dict[str, bytes] | None = None) -> int:
        """GET ``path``; with ``etags``, send the last ETag seen for it (a caching client) and remember the new."""
        extra = b""
        if etags is not None and path in etags:
            extra = b"If-None-Match: " + etags[path] + b"\r\n"
        self.writer.write(f"GET {path} HTTP/1.1\r\nHost: bench\r\n".encode() + self.auth + extra + b"\r\n")
        head = await self.reader.readuntil(b"\r\n\r\n")
        length = re.search(rb"(?i)\r\ncontent-length: *(\d+)", head)
        if length:
            await self.reader.readexactly(int(length.group(1)))
        if etags is not None and (tag := re.search(rb"(?i)\r\netag: *([^\r]+)", head)):
            etags[path] = tag.group(1)
        return int(head[9:12])

    def close(self) -> None:
        self.writer.close()


async def open_loop(
    base: str, key: str, job_ids: list[str], rate: float, duration: float, conditional: bool = False
) -> PollFigures:
    """Requests are due on a fixed schedule whatever the answers do; latency counts from the due time, so
    time spent waiting for a free connection is included (no coordinated omission). ``conditional``: each
    request carries the ETag of the last answer for that job (If-None-Match), as a caching client does."""
    conns = [await Connection.open(base, key) for _ in range(OPEN_LOOP_CONNECTIONS)]
    due: asyncio.Queue[tuple[int, float] | None] = asyncio.Queue()
    latencies: list[float] = []
    errors = not_modified = 0
    etags: dict[str, bytes] | None = {} if conditional else None
    n = int(rate * duration)

    async def produce() -> None:
        start = time.perf_counter()
        for i in range(n):
            at = start + i / rate
            if (delay := at - time.perf_counter()) > 0:
                await asyncio.sleep(delay)
            due.put_nowait((i, at))
        for _ in conns:
            due.put_nowait(None)

    async def consume(conn: Connection) -> None:
        nonlocal errors, not_modified
        while (item := await due.get()) is not None:
            i, at = item
            status = await conn.get(f"/v1/jobs/{job_ids[i % len(job_ids)]}", etags)
            latencies.append(time.perf_counter() - at)
            errors += status not in (200, 304)
            not_modified += status == 304

    t0 = time.perf_counter()
    await asyncio.gather(produce(), *(consume(c) for c in conns))
    elapsed = time.perf_counter() - t0
    for c in conns:
        c.close()
    lat = np.array(latencies) * 1e3
    mode = f"open loop {rate:.0f}/s ({len(conns)}){', If-None-Match' if conditional else ''}"
    figures = PollFigures(mode, n, errors, elapsed, *np.percentile(lat, [50, 99]))
    figures.not_modified = not_modified
    return figures


async def closed_loop(base: str, key: str, job_ids: list[str], concurrency: int, duration: float) -> PollFigures:
    """``concurrency`` connections, each sending its next request as soon as the last is answered."""
    conns = [await Connection.open(base, key) for _ in range(concurrency)]
    latencies: list[float] = []
    errors = 0
    stop = time.perf_counter() + duration

    async def worker(w: int) -> None:
        nonlocal errors
        i = w
        while time.perf_counter() < stop:
            t0 = time.perf_counter()
            status = await conns[w].get(f"/v1/jobs/{job_ids[i % len(job_ids)]}")
            latencies.append(time.perf_counter() - t0)
            errors += status != 200
            i += concurrency

    start = time.perf_counter()
    await asyncio.gather(*(worker(w) for w in range(concurrency)))
    elapsed = time.perf_counter() - start
    for c in conns:
        c.close()
    lat = np.array(latencies) * 1e3
    return PollFigures(f"closed loop x{concurrency}", len(lat), errors, elapsed, *np.percentile(lat, [50, 99]))


@contextmanager
def refining_workers(url: str, queue: JobQueue, owner: str, workers: int) -> Iterator[None]:
    """``hoi-refine worker --workers N`` refining the built-in example sequence (2 jobs per worker, ahead of
    the polled jobs by priority) until the block ends; waits until N jobs are RUNNING."""
    if workers <= 0:
        yield
        return
    payload = sequence_to_npz_bytes(example_sequence(seed=0).validate())
    for i in range(2 * workers):
        queue.submit(owner, payload, JobOptions(seed=i, priority=10), None, f"example-{i}", 72)
    env = {**os.environ, "HOI_REFINE_DATABASE_URL": url}
    cmd = [sys.executable, "-m", "common.cli", "worker", "--workers", str(workers), "--quiet-actors"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, start_new_session=True, stdout=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 180
        while running_jobs(queue) < workers:
            if time.monotonic() > deadline or proc.poll() is not None:
                raise SystemExit(f"the workers did not start refining (exit code {proc.poll()})")
            time.sleep(1.0)
        yield
    finally:
        proc.send_signal(signal.SIGTERM)  # graceful: running jobs are released to QUEUED
        try:
            proc.wait(timeout=90)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)


def running_jobs(queue: JobQueue) -> int:
    return queue.stats().jobs_by_state.get("RUNNING", 0)


def bench_polling(url: str, args: argparse.Namespace) -> list[PollFigures]:
    engine = create_engine_for(url)
    queue = JobQueue(engine, Settings(max_active_jobs_per_key=100_000))
    owner, key = ApiKeyStore(engine).create("bench")
    try:
        with refining_workers(url, queue, owner, args.refine_workers):
            return _poll_runs(url, key, queue, args)
    finally:
        engine.dispose()


def _poll_runs(url: str, key: str, queue: JobQueue, args: argparse.Namespace) -> list[PollFigures]:
    with server(url) as (base, pid):
        body = {**sequence_to_json_dict(tiny_sequence().validate()), "options": {}}
        job_ids = []
        for i in range(args.poll_jobs):
            body["options"] = {"seed": i}
            resp = httpx.post(f"{base}/v1/jobs", json=body, headers={"Authorization": f"Bearer {key}"}, timeout=30)
            resp.raise_for_status()
            job_ids.append(resp.json()["id"])
        asyncio.run(open_loop(base, key, job_ids, args.rate, 2.0))  # warm-up
        out = []
        for run in (
            lambda: open_loop(base, key, job_ids, args.rate, args.duration),
            lambda: open_loop(base, key, job_ids, args.rate, args.duration, conditional=True),
            lambda: closed_loop(base, key, job_ids, args.concurrency, args.closed_duration),
        ):
            before = running_jobs(queue)
            cpu0 = process_cpu_seconds(pid)
            figures = asyncio.run(run())
            figures.server_cpu_ms = (process_cpu_seconds(pid) - cpu0) / figures.requests * 1e3
            figures.running = f"{before}/{running_jobs(queue)}"
            out.append(figures)
    return out


def bench_claims(url: str, jobs: int, claimers: int) -> ClaimFigures:
    engine = create_engine_for(url)
    queue = JobQueue(engine, Settings(max_active_jobs_per_key=1_000_000))
    owner, _ = ApiKeyStore(engine).create("bench")
    payload = tiny_payload()
    for i in range(jobs):
        queue.submit(owner, payload, JobOptions(seed=i), None, f"bench-{i}", 5)
    queued = queue.stats().jobs_by_state.get("QUEUED", 0)  # these plus the polling run's jobs
    per_claimer, seconds = run_claimers(url, claimers)
    claimed = [j for done in per_claimer for j in done]
    left = queue.stats().jobs_by_state.get("QUEUED", 0)
    engine.dispose()
    assert len(set(claimed)) == queued and left == 0, f"{len(set(claimed))} jobs claimed of {queued}, {left} left"
    return ClaimFigures(len(claimed), claimers, seconds, len(claimed) - len(set(claimed)))


def report(results: dict[str, tuple[list[PollFigures], ClaimFigures]], args: argparse.Namespace) -> str:
    lines = [
        "# API load benchmark (`bench/api_load.py`)",
        "",
        f"Run {datetime.now(UTC):%Y-%m-%d %H:%M} UTC on {platform.node() or 'this machine'}: "
        f"{os.cpu_count()} CPU cores shared by the client, one uvicorn worker and the database; Python "
        f"{platform.python_version()}. Command: `.venv/bin/python bench/api_load.py "
        f"--rate {args.rate:g} --duration {args.duration:g} --claim-jobs {args.claim_jobs} "
        f"--claimers {args.claimers} --refine-workers {args.refine_workers}`. Load average (1/5/15 min) before: "
        f"{'/'.join(f'{x:.1f}' for x in args.load_before)}, after: {'/'.join(f'{x:.1f}' for x in args.load_after)}"
        " (other work on the machine competes for the same cores). Refinement workers on the same machine: "
        f"{args.refine_workers} (`hoi-refine worker --workers {args.refine_workers}`, nice "
        f"{Settings().worker_nice}, refining the built-in example sequence throughout the polling runs).",
        "",
        "## Status polling: `GET /v1/jobs/{id}` (auth, ETag, progress) against a uvicorn subprocess",
        "",
        "| backend | load (connections) | jobs refining (start/end) | requests | errors | 304s | achieved req/s "
        "| p50 ms | p99 ms | server CPU ms/request |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for backend, (polls, _) in results.items():
        for p in polls:
            lines.append(f"| {backend} | {p.mode} | {p.running} | {p.requests} | {p.errors} | {p.not_modified} | "
                         f"{p.rate:.0f} | {p.p50_ms:.1f} | {p.p99_ms:.1f} | {p.server_cpu_ms:.2f} |")  # fmt: skip
    lines += [
        "",
        f"## Claim throughput: {args.claimers} claimer processes, claim + complete until the queue is empty",
        "",
        "| backend | jobs | claimers | seconds | claims/s | jobs claimed twice |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for backend, (_, c) in results.items():
        lines.append(f"| {backend} | {c.jobs} | {c.claimers} | {c.seconds:.2f} | {c.jobs / c.seconds:.0f} | "
                     f"{c.duplicates} |")  # fmt: skip
    lines += [
        "",
        "## Reading the figures",
        "",
        "- The open-loop run keeps sending at the target rate whatever the answers do and measures latency from "
        "each request's due time, so when the machine cannot keep up the backlog shows in p50/p99 (no "
        "coordinated omission). The closed-loop run shows the rate the whole setup saturates at.",
        "- Client, server and database share the same cores with whatever else runs on the machine (see the "
        "load average above), so req/s and latencies understate a dedicated host. *Server CPU ms/request* "
        "(uvicorn's own CPU time divided by its requests) does not depend on that: one free core serves about "
        "1000 / that figure requests per second.",
        "- Claims: each claim is a write transaction (SQLite: BEGIN IMMEDIATE; PostgreSQL: FOR UPDATE SKIP LOCKED) "
        "followed by a second one that stores the result; *jobs claimed twice* must be 0.",
    ]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--backends", default="sqlite,postgres")
    parser.add_argument("--postgres-url", default=os.environ.get("HOI_REFINE_TEST_POSTGRES_URL"))
    parser.add_argument("--rate", type=float, default=200.0, help="open-loop polling rate, requests/s")
    parser.add_argument("--duration", type=float, default=30.0, help="open-loop seconds")
    parser.add_argument("--concurrency", type=int, default=16, help="closed-loop clients")
    parser.add_argument("--closed-duration", type=float, default=10.0)
    parser.add_argument("--poll-jobs", type=int, default=50, help="jobs submitted for polling")
    parser.add_argument("--claim-jobs", type=int, default=400)
    parser.add_argument("--claimers", type=int, default=8)
    parser.add_argument("--refine-workers", type=int, default=0,
                        help="run `hoi-refine worker --workers N` refining real sequences during the polling runs")
    parser.add_argument("--out", type=Path, help="also write the markdown report here")
    args = parser.parse_args()
    results = {}
    args.load_before = os.getloadavg()
    for backend in args.backends.split(","):
        with database(backend, args.postgres_url) as url:
            upgrade_to_head(url)
            polls = bench_polling(url, args)
            print(f"{backend}: polling {polls}", file=sys.stderr)
            claims = bench_claims(url, args.claim_jobs, args.claimers)
            print(f"{backend}: claims {claims}", file=sys.stderr)
            results[backend] = (polls, claims)
    args.load_after = os.getloadavg()
    text = report(results, args)
    print(text)
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
