"""``make compose-test``: the container stack proven on this machine (issue #20.4).

1. Images: the local base (``docker/build_base_image.sh``, skipped when it exists; ``--base-image
   python:3.11-slim`` where Docker Hub answers), then the project image (``docker build --network host``), timed.
2. Stack: docker-compose.yml + docker-compose.test.yml (host network, Ray GCS on 6380, the host's PostgreSQL in a
   database made for this run): API + Ray head + two worker containers; timed until both workers' actors run.
3. Kill test: ``--jobs`` short sequences (the built-in example, small CMA-ES budgets) go in through the API with
   a key made by ``hoi-refine keys create`` inside the API container; once the first worker container runs a
   job, ``docker kill`` (SIGKILL) takes that container down mid-job. Checked: every job ends SUCCEEDED, the killed
   job with attempt 2 and finished by the other container, one ``succeeded`` event and one stored result per job
   (through the API and the queue's event log in the database), and the killed container stays down.
4. Always (``finally``): ``compose down -v`` (bounded), no container of the project left, database dropped.

    .venv/bin/python bench/compose_test.py                     # prints the figures
    .venv/bin/python bench/compose_test.py --out bench/results/compose.md

Needs a running dockerd, docker-compose (v1 or the v2 plugin), root for debootstrap, and the PostgreSQL server of
``--postgres-url`` (default ``HOI_REFINE_TEST_POSTGRES_URL`` or postgres@127.0.0.1:5432/test). Not part of
``make test``: it takes minutes and a Docker engine.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import uuid
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import sqlalchemy as sa

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # bench/ runs as a script

from bench.compose_stack import (  # noqa: E402
    Stack,
    StackError,
    build_base_image,
    build_image,
    check_engine,
    check_ports_free,
    image_size_mb,
    run,
)
from common.api_client import ApiClient  # noqa: E402
from common.database import create_engine_for  # noqa: E402
from common.job_options import JobOptions  # noqa: E402
from common.queue import JobQueue  # noqa: E402
from common.result_format import read_summary  # noqa: E402
from common.sequence_io import sequence_to_npz_bytes  # noqa: E402
from worker.example.sequences import short_example_sequence  # noqa: E402

API_URL = "http://127.0.0.1:18000"  # docker-compose.test.yml
WORKERS = ("worker-1", "worker-2")
VICTIM = "worker-1"
#: Seconds-long jobs on the 24-frame example (as the `up` acceptance test uses).
SHORT = JobOptions(max_generations=3, popsize=8)
TERMINAL = ("SUCCEEDED", "FAILED", "CANCELLED")
DEFAULT_PG = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


@dataclass
class Figures:
    engine: str = ""
    compose: str = ""
    base_image: str = ""
    base_build_s: float | None = None
    image_build_s: float = 0.0
    no_cache: bool = False
    image_mb: float = 0.0
    stack_up_s: float = 0.0
    stack_ready_s: float = 0.0
    #: `ray start` attempts of the worker containers that timed out and were retried (a loaded machine).
    node_start_retries: int = 0
    #: Worker id -> the compose service (container) whose log announced it.
    worker_service: dict[str, str] = field(default_factory=dict)
    jobs: list[dict[str, Any]] = field(default_factory=list)
    victim_job: str = ""
    victim_progress: dict[str, Any] = field(default_factory=dict)
    killed_state: dict[str, Any] = field(default_factory=dict)
    all_done_s: float = 0.0
    down_s: float = 0.0
    checks: list[str] = field(default_factory=list)
    error: str = ""


def _admin_engine(url: str) -> sa.Engine:
    return sa.create_engine(url, isolation_level="AUTOCOMMIT")


def _database_url(admin_url: str, name: str) -> str:
    return sa.make_url(admin_url).set(database=name).render_as_string(hide_password=False)


def _wait(client: ApiClient, ids: list[str], pred: Any, timeout: float, what: str) -> list[dict[str, Any]]:
    deadline = time.monotonic() + timeout
    while True:
        jobs = [client.job(i)[0] for i in ids]
        if pred(jobs):
            return jobs
        if time.monotonic() > deadline:
            raise StackError(f"timed out after {timeout:.0f} s waiting for {what}: {[j['state'] for j in jobs]}")
        time.sleep(0.2)


def _victim(jobs: list[dict[str, Any]], victim_ids: set[str], queue: JobQueue) -> dict[str, Any] | None:
    """A job the victim container is refining right now, one CMA-ES generation or more into it."""
    for job in jobs:
        p = job.get("progress") or {}
        if job["state"] != "RUNNING" or (p.get("evaluations") or 0) < (SHORT.popsize or 1):
            continue
        if queue.get(None, job["id"]).worker_id in victim_ids:  # the API does not say who holds a job; the row does
            return job
    return None


def scenario(stack: Stack, db_url: str, n_jobs: int, timeout: float, fig: Figures) -> None:
    t0 = time.monotonic()
    stack.up(timeout=600)
    fig.stack_up_s = time.monotonic() - t0
    worker_ids = stack.wait_for_workers(WORKERS, per_service=1, timeout=300)
    fig.stack_ready_s = time.monotonic() - t0
    fig.worker_service = {wid: svc for svc, ids in worker_ids.items() for wid in ids}
    fig.node_start_retries = sum(stack.logs(w).count("could not join Ray cluster") for w in WORKERS)
    print(f"stack up in {fig.stack_up_s:.1f} s, worker actors running after {fig.stack_ready_s:.1f} s", flush=True)

    key = stack.exec("api", "hoi-refine", "keys", "create", "compose-test").strip().splitlines()[-1]
    client = ApiClient(API_URL, key)
    queue = JobQueue(create_engine_for(db_url))
    try:
        payloads = [sequence_to_npz_bytes(short_example_sequence(seed=i)) for i in range(n_jobs)]
        ids = [
            client.submit(p, f"seq{i}.npz", SHORT.model_copy(update={"seed": i}))["id"] for i, p in enumerate(payloads)
        ]
        t_submit = time.monotonic()
        print(f"submitted {n_jobs} jobs", flush=True)

        # Kill the first worker container while it runs a job (not before: the kill must interrupt one).
        found: list[dict[str, Any]] = []

        def victim_running(jobs: list[dict[str, Any]]) -> bool:
            job = _victim(jobs, worker_ids[VICTIM], queue)
            found[:] = [job] if job else []
            return job is not None

        _wait(client, ids, victim_running, 300, f"{VICTIM} to run a job")
        victim = found[0]
        container = stack.container(VICTIM)
        run(["docker", "kill", container], timeout=60)  # SIGKILL: no graceful release of the job
        fig.victim_job, fig.victim_progress = victim["id"], victim.get("progress") or {}
        print(f"docker kill {VICTIM} while it ran job {victim['id']} ({fig.victim_progress})", flush=True)

        done = _wait(client, ids, lambda js: all(j["state"] in TERMINAL for j in js), timeout, "every job to end")
        fig.all_done_s = time.monotonic() - t_submit
        fig.killed_state = stack.inspect_state(container)
        fig.jobs = [{"worker": queue.get(None, j["id"]).worker_id, **{k: j[k] for k in ("id", "state", "attempt")}}
                    for j in done]  # fmt: skip
        _check(fig, client, queue, done, ids, worker_ids)
    finally:
        client.close()
        queue.engine.dispose()


def _check(fig: Figures, client: ApiClient, queue: JobQueue, done: list[dict[str, Any]], ids: list[str],
           worker_ids: dict[str, set[str]]) -> None:  # fmt: skip
    states = [j["state"] for j in done]
    assert states == ["SUCCEEDED"] * len(ids), [(j["state"], j.get("errors")) for j in done]
    fig.checks.append(f"all {len(ids)} jobs SUCCEEDED (API)")
    attempts = {j["id"]: j["attempt"] for j in done}
    assert attempts[fig.victim_job] == 2, attempts
    assert sorted(attempts.values()) == [1] * (len(ids) - 1) + [2], attempts
    fig.checks.append("the killed job took attempt 2, every other job attempt 1 (API)")
    finisher = queue.get(None, fig.victim_job).worker_id
    assert finisher in worker_ids["worker-2"], (finisher, worker_ids)
    fig.checks.append("the killed job was finished by worker-2's actor (its worker id in the database)")
    for job_id in ids:
        summary = read_summary(client.result(job_id))
        assert summary, job_id
    fig.checks.append("every result downloads as NPZ and its summary reads back (API)")

    for job_id in ids:
        kinds = [e.kind for e in queue.events(None, job_id)]
        assert kinds.count("succeeded") == 1, (job_id, kinds)
        queue.get_result(None, job_id)  # one row: job_results is keyed by job id
        if job_id == fig.victim_job:
            assert kinds.count("requeued") == 1 and kinds.count("claimed") == 2, kinds
        else:
            assert kinds.count("claimed") == 1 and "requeued" not in kinds, (job_id, kinds)
    fig.checks.append("one `succeeded` event and one stored result per job; the killed job: claimed twice, "
                      "requeued once after its lease expired (database event log)")  # fmt: skip
    state = fig.killed_state
    assert not state["Running"] and state["ExitCode"] == 137 and state["RestartCount"] == 0, state
    fig.checks.append("the killed container stayed down (exit 137, no restart)")


def report(fig: Figures, args: argparse.Namespace) -> str:
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    flags = f"--jobs {args.jobs} --lease-seconds {args.lease_seconds:g}"
    flags += " --no-cache" * fig.no_cache + " --rebuild-base" * args.rebuild_base
    base = "existed (not rebuilt)" if fig.base_build_s is None else f"{fig.base_build_s:.0f} s (debootstrap + import)"
    build = "`docker build --network host`" + (", --no-cache" if fig.no_cache else ", cached layers")
    retried = ""
    if fig.node_start_retries:
        retried = f" (incl. {fig.node_start_retries} `ray start` retried after Ray's 30 s node registration timeout)"
    killed = ""
    if fig.victim_job:
        p = fig.victim_progress
        killed = (
            f" `docker kill` hit {VICTIM} while it ran job `{fig.victim_job}` (window {p.get('window')}/"
            f"{p.get('windows')}, {p.get('evaluations')} evaluations in)."
        )
    lines = [
        "# Containers: build, start, kill a worker mid-job (`make compose-test`)",
        "",
        f"Last run: {when}, `bench/compose_test.py {flags}`. Machine: {os.cpu_count()} shared cores, loaded "
        f"(other sessions running), {platform.machine()}; Docker engine {fig.engine}, {fig.compose}.",
        "",
        "| step | figure |",
        "|---|---|",
        f"| base image `{fig.base_image}` | {base} |",
        f"| project image build ({build}) | {fig.image_build_s:.0f} s, {fig.image_mb:.0f} MB |",
        f"| stack start (`up -d` until every service it waits on is healthy) | {fig.stack_up_s:.1f} s |",
        f"| stack ready (both worker containers' actors running) | {fig.stack_ready_s:.1f} s{retried} |",
        f"| {args.jobs} jobs from submission to all finished, one worker killed | {fig.all_done_s:.1f} s |",
        f"| tear-down (`down -v`) | {fig.down_s:.1f} s |",
        "",
        f"Kill test: **{'FAILED' if fig.error else 'PASSED'}**.{killed}",
        "",
        *[f"* {c}" for c in fig.checks],
        *([f"* error: `{fig.error}`"] if fig.error else []),
        "",
        "| job | state | attempt | finished by |",
        "|---|---|---|---|",
        *[
            f"| `{j['id']}` | {j['state']} | {j['attempt']} | {fig.worker_service.get(j['worker'], '?')} "
            f"(`{j['worker']}`) |"
            for j in fig.jobs
        ],
        "",
        "Stack: docker-compose.yml + docker-compose.test.yml, every container on the host network, all traffic on "
        "loopback: API on 127.0.0.1:18000, Ray on 127.0.0.2 with its GCS on 6380 (Redis holds 6379), the host's "
        "PostgreSQL at 127.0.0.1:5432 in a database created for the run and dropped after (Ray still listens on "
        "all interfaces for its GCS, node manager and object manager: it binds them so whatever the node IP); "
        "1 worker actor x 1 thread per worker container; "
        f"`HOI_REFINE_LEASE_SECONDS={args.lease_seconds:g}` so the killed job's lease runs out quickly. Jobs: the "
        f"24-frame built-in example, seeds 0..{args.jobs - 1}, `max_generations=3, popsize=8`.",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--jobs", type=int, default=4, help="short sequences to submit (default 4)")
    ap.add_argument("--base-image", default="hoi-refine-base:bookworm",
                    help="BASE_IMAGE of the Dockerfile; hoi-refine-base:* is built locally when missing "
                    "(default hoi-refine-base:bookworm)")  # fmt: skip
    ap.add_argument("--no-cache", action="store_true", help="build the project image from scratch")
    ap.add_argument("--rebuild-base", action="store_true", help="rebuild the local base image even if it exists")
    ap.add_argument("--lease-seconds", type=float, default=8.0, help="worker lease (default 8 s)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds for the jobs to end (default 900)")
    ap.add_argument("--postgres-url", default=os.environ.get("HOI_REFINE_TEST_POSTGRES_URL", DEFAULT_PG),
                    help="a PostgreSQL server the test may create and drop a database on")  # fmt: skip
    ap.add_argument("--out", type=Path, default=None, help="write the report (markdown) here")
    args = ap.parse_args(argv)
    if args.jobs < 2:
        ap.error("--jobs must be >= 2 (one job is killed, the others show the survivor keeps working)")

    fig = Figures(base_image=args.base_image, no_cache=args.no_cache)
    fig.engine = check_engine()
    check_ports_free()
    if args.base_image.startswith("hoi-refine-base:"):
        fig.base_build_s = build_base_image(args.base_image, force=args.rebuild_base)
    print(f"building {args.base_image} -> hoi-refine:latest ...", flush=True)
    fig.image_build_s = build_image(args.base_image, args.no_cache)
    fig.image_mb = image_size_mb()
    print(f"image built in {fig.image_build_s:.0f} s ({fig.image_mb:.0f} MB)", flush=True)

    db_name = f"hoi_refine_compose_{uuid.uuid4().hex[:10]}"
    db_url = _database_url(args.postgres_url, db_name)
    admin = _admin_engine(args.postgres_url)
    with admin.connect() as conn:
        conn.exec_driver_sql(f"CREATE DATABASE {db_name}")
    env = {
        **os.environ,
        "COMPOSE_TEST_DATABASE_URL": db_url,
        "HOI_REFINE_BASE_IMAGE": args.base_image,
        "HOI_REFINE_LEASE_SECONDS": str(args.lease_seconds),
        "HOI_REFINE_WORKERS_PER_CONTAINER": "1",
        "HOI_REFINE_THREADS_PER_WORKER": "1",
    }
    stack = Stack(project="hoi-refine-compose-test", env=env)
    fig.compose = stack.version()
    log_dir = ROOT / "var" / "compose-test"
    try:
        scenario(stack, db_url, args.jobs, args.timeout, fig)
    except Exception as exc:  # recorded in the report, then raised
        fig.error = f"{type(exc).__name__}: {exc}"[:2000]
        raise
    finally:
        log_dir.mkdir(parents=True, exist_ok=True)
        (log_dir / "compose.log").write_text(stack.logs())
        fig.down_s = stack.down()
        with admin.connect() as conn:
            conn.exec_driver_sql(f"DROP DATABASE IF EXISTS {db_name} WITH (FORCE)")
        admin.dispose()
        text = report(fig, args)
        print(text)
        if args.out:
            args.out.write_text(text)
        print(f"container logs: {log_dir / 'compose.log'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
