"""Worker throughput: sequences per hour for 1 worker x 1 thread, 1 x 2 and 2 x 1 (issue #5, "must show").

    .venv/bin/python bench/throughput.py [--sample dev40] [--count 12] [--passes 2] [--popsize P] [--max-generations G]

For each configuration: a fresh SQLite queue, the same ``--count`` DexYCB development sequences (the first
lines of ``bench/samples/<sample>.txt``, read from ../shared/data) submitted as jobs, then a ``WorkerPool``
(local Ray, the production actors and refinement) drains the queue. Throughput counts from the first claim
to the last completion, so Ray's start-up is excluded; it is reported separately. The share of worker wall
time inside simulation is the sum of the jobs' ``timings.sim_s`` (seconds inside MuJoCo rollouts and
replays, measured by the evaluator) over the sum of their run times (claim to completion). The configurations
run ``--passes`` times, every other pass in reverse order (1x1, 1x2, 2x1, then 2x1, 1x2, 1x1): a shared machine's
speed drifts over the minutes one pass takes, and the mirrored order cancels a steady drift from the ratios.
Writes ``bench/results/throughput.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CONFIGS: tuple[tuple[int, int], ...] = ((1, 1), (1, 2), (2, 1))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sample", default="dev40", help="sample list in bench/samples (default dev40)")
    p.add_argument("--count", type=int, default=12, help="sequences per configuration (default 12)")
    p.add_argument("--popsize", type=int, default=None, help="CMA-ES population (default: the product's)")
    p.add_argument("--max-generations", type=int, default=None, help="CMA-ES generations per window")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--passes", type=int, default=2,
                   help="passes over the configurations, every other one in reverse order (default 2): this "
                        "machine's speed drifts over minutes, and 1x1, 1x2, 2x1 then 2x1, 1x2, 1x1 cancels a steady "
                        "drift from the ratios")  # fmt: skip
    p.add_argument("--configs", type=parse_configs, default=CONFIGS, metavar="WxT,...",
                   help="workers x threads to run, e.g. 1x2 (default 1x1,1x2,2x1)")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "throughput.md")
    return p.parse_args(argv)


def parse_configs(text: str) -> tuple[tuple[int, int], ...]:
    try:
        configs = tuple((int(w), int(t)) for w, t in (item.lower().split("x") for item in text.split(",")))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected workers x threads like 1x2,2x1, got {text!r}") from None
    if not configs or any(w < 1 or t < 1 for w, t in configs):
        raise argparse.ArgumentTypeError(f"workers and threads must be at least 1: {text!r}")
    return configs


def sample_files(sample: str, count: int) -> list[Path]:
    from common.dexycb import shared_data_dir

    data = shared_data_dir()
    if data is None:
        raise SystemExit("../shared/data is not present: the throughput benchmark reads real DexYCB sequences")
    lines = (ROOT / "bench" / "samples" / f"{sample}.txt").read_text().splitlines()
    names = [n.strip() for n in lines if n.strip() and not n.startswith("#")]
    return [data / "dexycb" / "dev" / n for n in names[:count]]


def run_config(workers: int, threads: int, payloads: list[tuple[str, bytes]], options: Any) -> dict[str, Any]:
    from common.api_key_store import ApiKeyStore
    from common.database import create_engine_for, upgrade_to_head
    from common.queue import JobQueue
    from common.settings import get_settings
    from worker.runtime.pool import PoolConfig, WorkerPool

    with tempfile.TemporaryDirectory(prefix="hoi-throughput-") as tmp:
        url = f"sqlite:///{Path(tmp) / 'queue.sqlite3'}"
        os.environ["HOI_REFINE_DATABASE_URL"] = url
        os.environ["HOI_REFINE_VAR_DIR"] = str(Path(tmp) / "var")
        get_settings.cache_clear()
        upgrade_to_head(url)
        queue = JobQueue(create_engine_for(url))
        owner, _ = ApiKeyStore(queue.engine).create("bench")
        ids = [queue.submit(owner, blob, options, None, name, 0)[0].id for name, blob in payloads]
        pool = WorkerPool(PoolConfig(workers=workers, threads_per_worker=threads, log_to_driver=False))
        load_before = os.getloadavg()[0]
        t0 = time.monotonic()
        pool.start()
        stop = threading.Event()
        try:
            while not all(queue.get(None, i).is_terminal for i in ids):
                pool.poll(1.0)
        finally:
            stop.set()
            pool.stop()
        total = time.monotonic() - t0
        jobs = [queue.get(None, i) for i in ids]
        failed = [j.id for j in jobs if j.state != "SUCCEEDED"]
        if failed:
            raise SystemExit(f"{len(failed)} job(s) did not succeed: {[queue.get(None, i).errors for i in failed]}")
        first = min(j.started_at for j in jobs if j.started_at)
        last = max(j.finished_at for j in jobs if j.finished_at)
        span = (last - first).total_seconds()
        runs = [(j.finished_at - j.started_at).total_seconds() for j in jobs if j.finished_at and j.started_at]
        summaries = [queue.get_result(None, i)[1] for i in ids]
        sims = [float(s["timings"]["sim_s"]) for s in summaries]
        computes = [float(s["compute_seconds"]) for s in summaries]
        previews = [float(s.get("preview", {}).get("seconds", 0.0)) for s in summaries]
        return {
            "workers": workers,
            "threads": threads,
            "jobs": len(ids),
            "runs": runs,
            "computes": computes,
            "previews": previews,
            "sims": sims,
            "span_s": span,
            "total_s": total,
            "startup_s": total - span,
            "per_hour": len(ids) * 3600.0 / span,
            "mean_run_s": sum(runs) / len(runs),
            # The refinement and its verification alone, without the preview (the worker times it).
            "mean_compute_s": sum(computes) / len(computes),
            "mean_preview_s": sum(previews) / len(previews),
            "steady_per_hour": steady_rate(jobs),
            "sim_share": sum(sims) / sum(runs),
            # 1-minute load average before and after: the machine is shared, so say how busy it was.
            "load": (load_before, os.getloadavg()[0]),
        }


def steady_rate(jobs: list[Any]) -> float:
    """A dataset's rate, without the tail of a short run where one worker is idle (with a handful of jobs the span's
    last job often runs alone, which the span-based rate counts): each worker's jobs over its own span, from its
    first claim to its last result, summed over workers. With one worker it is the span's rate."""
    spans: dict[str, list[Any]] = {}
    for j in jobs:
        spans.setdefault(j.worker_id or "?", []).append(j)
    rate = 0.0
    for own in spans.values():
        span = (max(j.finished_at for j in own) - min(j.started_at for j in own)).total_seconds()
        rate += len(own) * 3600.0 / span
    return rate


def combine(passes: list[dict[str, Any]]) -> dict[str, Any]:
    """One configuration over all passes: rates over the summed spans, means over all jobs."""
    runs = [x for r in passes for x in r["runs"]]
    computes = [x for r in passes for x in r["computes"]]
    previews = [x for r in passes for x in r["previews"]]
    span = sum(r["span_s"] for r in passes)
    return {
        "workers": passes[0]["workers"],
        "threads": passes[0]["threads"],
        "pass": "all",
        "span_s": span,
        "startup_s": sum(r["startup_s"] for r in passes) / len(passes),
        "per_hour": sum(r["jobs"] for r in passes) * 3600.0 / span,
        "mean_run_s": sum(runs) / len(runs),
        "mean_compute_s": sum(computes) / len(computes),
        "mean_preview_s": sum(previews) / len(previews),
        "steady_per_hour": sum(r["steady_per_hour"] for r in passes) / len(passes),
        "sim_share": sum(x for r in passes for x in r["sims"]) / sum(runs),
        "load": (min(r["load"][0] for r in passes), max(r["load"][1] for r in passes)),
    }


def write_report(
    path: Path, rows: list[dict[str, Any]], files: list[Path], args: argparse.Namespace, each: list[dict[str, Any]]
) -> None:
    """``rows``: one per configuration (``combine``d); ``each``: every pass's rows in the order they ran."""
    from common.settings import get_settings

    settings = get_settings()
    cpu = os.cpu_count()
    lines = [
        "# Worker throughput (issue #5)",
        "",
        f"Generated by `bench/throughput.py` on {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {platform.machine()}, "
        f"{cpu} CPU cores, Python {platform.python_version()}.",
        f"Jobs: the same {len(files)} DexYCB development sequences per configuration "
        f"(`bench/samples/{args.sample}.txt`, first {len(files)}), CMA-ES popsize "
        f"{args.popsize or 'default'}, max generations {args.max_generations or 'default'}, seed {args.seed}; "
        "SQLite queue, local Ray, the production worker actors "
        f"(worker nice {settings.worker_nice}, preview thread nice +{settings.preview_nice}).",
        "",
        "| workers x threads | pass | sequences / hour | span s (first claim to last result) "
        "| mean job s (claim to result) "
        "| mean computation s (refinement + verification) | mean preview s | "
        "steady sequences / hour (each worker over its own span) | "
        "Ray + actor start-up s | share of worker wall time in simulation | load avg before / after |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in [*each, *rows]:
        lines.append(
            f"| {r['workers']} x {r['threads']} | {r['pass']} | {r['per_hour']:.1f} | {r['span_s']:.1f} "
            f"| {r['mean_run_s']:.1f} "
            f"| {r['mean_compute_s']:.1f} | {r['mean_preview_s']:.1f} | {r['steady_per_hour']:.1f} "
            f"| {r['startup_s']:.1f} | {100 * r['sim_share']:.0f}% | {r['load'][0]:.1f} / {r['load'][1]:.1f} |"
        )
    single = next((r for r in rows if (r["workers"], r["threads"]) == (1, 1)), None)
    if single is None:
        against = "No 1 x 1 run (`--configs`), so no ratios."
    else:
        base, steady = single["per_hour"], single["steady_per_hour"]
        speedups = ", ".join(
            f"{r['workers']} x {r['threads']}: x{r['per_hour'] / base:.2f} "
            f"(steady x{r['steady_per_hour'] / steady:.2f})"
            for r in rows if r is not single
        )
        per_job = "".join(
            f" One sequence on {r['threads']} threads took x{r['mean_compute_s'] / single['mean_compute_s']:.2f} of "
            f"its 1-thread time to compute (refinement and verification), "
            f"x{r['mean_run_s'] / single['mean_run_s']:.2f} from claim to stored result (with its preview, and on "
            "more than one thread the previous job's preview drawn beside it)."
            for r in rows if r["workers"] == 1 and r["threads"] > 1
        )
        against = (
            "Against 1 x 1, over the span (steady: each worker's jobs over its own span, the rate of a dataset much "
            f"longer than {len(files)} jobs): {speedups}.{per_job}"
        )
    # This benchmark's own workers make a load of up to the CPU count; more than that was someone else's work.
    shared = max(max(r["load"]) for r in each) > (cpu or 1) + 0.5
    load_text = (
        "The machine was shared while this ran (load average in the last column, on "
        f"{cpu} cores), so no configuration had both cores to itself: read the absolute figures as lower bounds "
        "and the 1 x 2 gain as depressed by the load."
        if shared
        else "Nothing else ran: the load average in the last column is this benchmark's own work."
    )
    lines += [
        "",
        f"Rows by pass in the order they ran ({args.passes} passes, every other one in reverse order, so that a "
        "steady drift of the machine's speed cancels from the ratios), then each configuration over all passes "
        "(rates over the summed spans). "
        f"{against} Within one worker only the rollouts of one CMA-ES "
        "generation run in parallel (popsize / threads each, then a barrier), and the result's raw and refined "
        "replays run side by side; the window probes and commits, the retargeting and the CMA-ES step on one "
        "thread. A worker of more than one thread draws a job's preview beside the next job's computation "
        "(`overlap_preview`); a 1-thread worker draws it between jobs, so it never takes a core beyond its one. "
        f"Separate workers overlap all of it. {load_text}",
        "",
        "Sequences:",
        "",
        *[f"- `{f.name}`" for f in files],
        "",
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from common.dexycb import load_dexycb_npz
    from common.job_options import JobOptions
    from common.sequence_io import sequence_to_npz_bytes

    files = sample_files(args.sample, args.count)
    payloads = [(f.stem, sequence_to_npz_bytes(load_dexycb_npz(f))) for f in files]
    options = JobOptions(seed=args.seed, popsize=args.popsize, max_generations=args.max_generations)
    if args.passes < 1:
        raise SystemExit("--passes must be at least 1")
    each: list[dict[str, Any]] = []
    for number in range(1, args.passes + 1):
        for workers, threads in args.configs if number % 2 else args.configs[::-1]:
            print(f"pass {number}: {workers} worker(s) x {threads} thread(s) ...", flush=True)
            row = {**run_config(workers, threads, payloads, options), "pass": number}
            print(f"  {row['per_hour']:.1f} sequences/hour, {100 * row['sim_share']:.0f}% in simulation", flush=True)
            each.append(row)
    rows = [combine([r for r in each if (r["workers"], r["threads"]) == config]) for config in args.configs]
    write_report(args.out, rows, files, args, each)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
