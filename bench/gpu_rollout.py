"""MuJoCo Warp rollouts against the CPU path (issue #19 item 5; optional: needs ``.[gpu]`` and, to mean much, a GPU).

    .venv/bin/python bench/gpu_rollout.py --sample dev120 --limit 3 --device cuda:0 --out bench/results/gpu.md

On real DexYCB sequences, three measurements, each printed as it finishes:

1. **Agreement.** Along a zero-offset pass through each sequence, at every ``--every``-th window, one CMA-ES
   population (``--popsize`` random candidates at the product's initial step size) rolled out by
   ``mujoco.rollout`` (float64, CPU) and by ``WarpEvaluator`` (float32, Warp device) from the same state:
   the object's position / rotation difference at the window's end, and whether the two rank the candidates
   alike (Spearman's rho of the window losses, and whether both pick the same best candidate), since CMA-ES only
   uses the ranking.
2. **Throughput.** One window with contacts, its population replicated to W worlds for each ``--worlds``:
   world-steps per second on the Warp device against ``mujoco.rollout`` on all CPU cores.
3. **Refinement.** ``--refine`` sequences refined with the product's options twice: CPU rollouts
   (``--threads``) and Warp rollouts. Seconds per sequence, physics steps, success, E_t / E_r (paper's protocol).
   Either way the result is the CPU replay of the chosen controls (``worker.refine.derive``).
4. **Pool** (``--parts ...,pool``): ``--pool-sequences`` sequences refined by ``--pool-size`` concurrent
   processes (one CPU thread each), once per ``--pool-backends`` entry: sequences per hour of the whole machine,
   the figure a dataset run sees (several Warp processes share the one GPU).

The report goes to ``--out`` (and stdout); nothing is cached.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sample", default="dev120", help="sample list in bench/samples (default dev120)")
    p.add_argument("--limit", type=int, default=3, help="sequences for the agreement check (default 3)")
    p.add_argument("--device", default=None, help="Warp device, e.g. cuda:0 or cpu (default: Warp's default)")
    p.add_argument("--every", type=int, default=4, help="check every N-th window (default 4)")
    p.add_argument("--popsize", type=int, default=None, help="population per check (default: the product's)")
    p.add_argument("--worlds", default="16,64,256,1024,4096", help="world counts for the throughput test")
    p.add_argument("--cpu-worlds-max", type=int, default=256,
                   help="largest world count also timed on the CPU (the CPU rate is flat beyond a few per core)")
    p.add_argument("--refine", type=int, default=2, help="sequences refined both ways (default 2; 0: skip)")
    p.add_argument("--threads", type=int, default=2, help="CPU threads for the CPU refinement (default 2)")
    p.add_argument("--parts", default="agreement,throughput,refine",
                   help="which measurements, in the order to run them, comma-separated, of agreement, throughput, "
                   "refine, pool (default: the first three)")
    p.add_argument("--pool-backends", default="cpu,warp", help="pool: rollout backends to run (default cpu,warp)")
    p.add_argument("--pool-size", type=int, default=os.cpu_count() or 1,
                   help="pool: concurrent refinement processes, 1 CPU thread each (default: one per core)")
    p.add_argument("--pool-sequences", type=int, default=16, help="pool: sequences of the sample (default 16)")
    p.add_argument("--max-generations", type=int, default=None,
                   help="CMA-ES generations per window for refine/pool (default: the product's; smoke tests only)")
    p.add_argument("--deadline-s", type=float, default=None,
                   help="stop starting new work after this many seconds (the report says what was skipped)")
    p.add_argument("--out", type=Path, default=None, help="markdown report (default: stdout only)")
    return p.parse_args(argv)


class Report:
    def __init__(self, out: Path | None) -> None:
        self.out = out
        self.lines: list[str] = []

    def add(self, *lines: str) -> None:
        for line in lines:
            print(line, flush=True)
            self.lines.append(line)
        if self.out is not None:  # written as it goes: a run stopped at a time limit keeps what it measured
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self.out.write_text("\n".join(self.lines) + "\n")


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    if np.std(ra) == 0 or np.std(rb) == 0:
        return float("nan")
    return float(np.corrcoef(ra, rb)[0, 1])


def _rot_deg(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    dot = np.abs(np.sum(qa * qb, axis=-1)) / (np.linalg.norm(qa, axis=-1) * np.linalg.norm(qb, axis=-1))
    return np.degrees(2 * np.arccos(np.clip(dot, -1.0, 1.0)))


def agreement(path: Path, args: argparse.Namespace, report: Report) -> list[dict[str, Any]]:
    """Checks along the zero-offset pass of one sequence (see the module docstring, item 1)."""
    from common.dexycb import load_dexycb_npz
    from common.job_options import JobOptions
    from common.settings import get_settings
    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.losses import resolve_weights
    from worker.refine.prepare import DEFAULT_POPSIZE, prepare, settled_start
    from worker.refine.replay import window_problem
    from worker.refine.warp_evaluator import WarpEvaluator

    prep = prepare(load_dexycb_npz(path), JobOptions(), cache_dir=get_settings().resolved_cache_dir())
    model = prep.scene.model
    rows = []
    with ParallelEvaluator(model, args.threads) as cpu, WarpEvaluator(model, device=args.device) as gpu:
        start, _ = settled_start(prep, cpu)
        weights = resolve_weights(None)
        on_cpu, on_gpu = window_problem(prep, cpu, start, weights), window_problem(prep, gpu, start, weights)
        keyframes = {s: np.zeros((on_cpu.n_keyframes, on_cpu.dim(s))) for s in on_cpu.sides}
        rng = np.random.default_rng(0)
        popsize = args.popsize or DEFAULT_POPSIZE
        state = on_cpu.start_state()
        for j in range(on_cpu.first_window, on_cpu.n_keyframes):
            if (j - on_cpu.first_window) % args.every == 0:
                cands = {s: 0.5 * rng.standard_normal((popsize, on_cpu.dim(s))) for s in on_cpu.sides}
                f0, f1 = on_cpu.window(j)
                control, _ = on_cpu.build_control(keyframes, f0, f1, j, cands)
                _, z_cpu = cpu.rollout(state, control)
                t0 = time.perf_counter()
                _, z_gpu = gpu.rollout(state, control)
                gpu_s = time.perf_counter() - t0
                p_cpu, q_cpu, _ = on_cpu.layout.object_from_sensors(z_cpu[:, -1])
                p_gpu, q_gpu, _ = on_cpu.layout.object_from_sensors(z_gpu[:, -1])
                loss_cpu = np.sum(list(on_cpu.evaluate(j, state, keyframes, cands).values()), axis=0)
                loss_gpu = np.sum(list(on_gpu.evaluate(j, state, keyframes, cands).values()), axis=0)
                p_first = on_cpu.layout.object_from_sensors(z_cpu[:, 0])[0]
                touching = bool(np.max(np.linalg.norm(p_cpu - p_first, axis=-1)) > 0.001)  # the object moves
                row = {
                    "window": j, "frames": f"{f0}-{f1}", "steps": control.shape[1], "touching": touching,
                    "dpos_mm_median": float(np.median(1000 * np.linalg.norm(p_cpu - p_gpu, axis=-1))),
                    "dpos_mm_max": float(np.max(1000 * np.linalg.norm(p_cpu - p_gpu, axis=-1))),
                    "drot_deg_max": float(np.max(_rot_deg(q_cpu, q_gpu))),
                    "rho": _spearman(loss_cpu, loss_gpu),
                    "same_best": bool(np.argmin(loss_cpu) == np.argmin(loss_gpu)),
                    "gpu_s": gpu_s,
                }
                rows.append(row)
                report.add(f"| {path.stem} | {j} ({row['frames']}) | {'yes' if touching else 'no'} | "
                           f"{row['dpos_mm_median']:.3f} / {row['dpos_mm_max']:.3f} | {row['drot_deg_max']:.3f} | "
                           f"{row['rho']:.3f} | {'yes' if row['same_best'] else 'no'} |")
            state = on_cpu.commit(j, state, keyframes)
    return rows


def throughput(path: Path, args: argparse.Namespace, report: Report) -> None:
    """World-steps per second of one contact-rich window's population (module docstring, item 2)."""
    from common.dexycb import load_dexycb_npz
    from common.job_options import JobOptions
    from common.settings import get_settings
    from worker.refine.evaluator import ParallelEvaluator
    from worker.refine.losses import resolve_weights
    from worker.refine.prepare import DEFAULT_POPSIZE, prepare, settled_start
    from worker.refine.replay import window_problem
    from worker.refine.warp_evaluator import WarpEvaluator

    prep = prepare(load_dexycb_npz(path), JobOptions(), cache_dir=get_settings().resolved_cache_dir())
    model = prep.scene.model
    cores = os.cpu_count() or 1
    with ParallelEvaluator(model, cores) as cpu, WarpEvaluator(model, device=args.device) as gpu:
        start, _ = settled_start(prep, cpu)
        problem = window_problem(prep, cpu, start, resolve_weights(None))
        keyframes = {s: np.zeros((problem.n_keyframes, problem.dim(s))) for s in problem.sides}
        j = max(problem.first_window, problem.n_keyframes // 2)  # mid-sequence: the hand holds the object
        state = problem.start_state()
        for k in range(problem.first_window, j):
            state = problem.commit(k, state, keyframes)
        f0, f1 = problem.window(j)
        rng = np.random.default_rng(0)
        popsize = args.popsize or DEFAULT_POPSIZE
        cands = {s: 0.5 * rng.standard_normal((popsize, problem.dim(s))) for s in problem.sides}
        control, _ = problem.build_control(keyframes, f0, f1, j, cands)
        report.add("", f"Window {j} (frames {f0}-{f1}, {control.shape[1]} steps) of {path.stem}; CPU: "
                   f"`mujoco.rollout` on {cores} threads.", "",
                   "| worlds | Warp world-steps/s | Warp s per rollout | CPU world-steps/s | Warp / CPU |",
                   "| ---: | ---: | ---: | ---: | ---: |")
        for worlds in [int(w) for w in args.worlds.split(",")]:
            batch = np.ascontiguousarray(np.resize(control, (worlds, *control.shape[1:])))
            gpu.rollout(state, batch)  # graph capture and first-touch allocations
            reps = max(1, min(5, 20_000 // worlds))
            t0 = time.perf_counter()
            for _ in range(reps):
                gpu.rollout(state, batch)
            gpu_s = (time.perf_counter() - t0) / reps
            gpu_rate = worlds * control.shape[1] / gpu_s
            cpu_rate = float("nan")
            if worlds <= args.cpu_worlds_max:
                cpu.rollout(state, batch)
                t0 = time.perf_counter()
                cpu.rollout(state, batch)
                cpu_rate = worlds * control.shape[1] / (time.perf_counter() - t0)
            report.add(f"| {worlds} | {gpu_rate:,.0f} | {gpu_s:.3f} | {cpu_rate:,.0f} | "
                       f"{gpu_rate / cpu_rate if cpu_rate == cpu_rate else float('nan'):.2f} |")


def refine_both(path: Path, args: argparse.Namespace, report: Report) -> None:
    """The product's refinement with CPU rollouts, then with Warp rollouts (module docstring, item 3)."""
    from common.dexycb import load_dexycb_npz
    from common.settings import get_settings
    from worker.refine.run import refine_sequence
    from worker.refine.warp_evaluator import WarpEvaluator

    seq = load_dexycb_npz(path)
    cache = get_settings().resolved_cache_dir()
    for backend in ("cpu", "warp"):
        t0 = time.perf_counter()
        if backend == "cpu":
            outcome = refine_sequence(seq, _options(args.max_generations), threads=args.threads, cache_dir=cache)
        else:
            import mujoco

            with WarpEvaluator(mujoco.MjModel.from_xml_string("<mujoco/>"), device=args.device) as ev:
                outcome = refine_sequence(seq, _options(args.max_generations), evaluator=ev, cache_dir=cache)
        wall = time.perf_counter() - t0
        m = outcome.summary["metrics"]["refined"]
        paper = m.get("paper", m)
        t = outcome.summary["timings"]
        report.add(f"| {path.stem} ({seq.hands[0].side}, {seq.object.name}) | {backend} | {wall:.1f} | "
                   f"{t['rollout_s']:.1f} | {t['steps']:,} | {len(outcome.summary.get('attempts', []))} | "
                   f"{'ok' if m['success'] else 'FAIL'} | {paper['E_t']:.2f} | {paper['E_r']:.2f} |")


def _options(args_max_generations: int | None) -> Any:
    from common.job_options import JobOptions

    return JobOptions(max_generations=args_max_generations)


def pool_job(task: tuple[str, str, str | None, int | None]) -> dict[str, Any]:
    """One pool task (a separate process): refine one sequence with CPU or Warp rollouts, one CPU thread."""
    path, backend, device, max_generations = task
    import mujoco

    from common.dexycb import load_dexycb_npz
    from common.settings import get_settings
    from worker.refine.run import refine_sequence

    seq = load_dexycb_npz(Path(path))
    cache = get_settings().resolved_cache_dir()
    t0 = time.perf_counter()
    if backend == "cpu":
        outcome = refine_sequence(seq, _options(max_generations), threads=1, cache_dir=cache)
    else:
        from worker.refine.warp_evaluator import WarpEvaluator

        with WarpEvaluator(mujoco.MjModel.from_xml_string("<mujoco/>"), device=device) as ev:
            outcome = refine_sequence(seq, _options(max_generations), evaluator=ev, cache_dir=cache)
    m = outcome.summary["metrics"]["refined"]
    paper = m.get("paper", m)
    return {"name": Path(path).stem, "wall_s": time.perf_counter() - t0, "success": bool(m["success"]),
            "E_t": float(paper["E_t"]), "E_r": float(paper["E_r"]), "steps": int(outcome.summary["timings"]["steps"])}


def pool(paths: list[Path], args: argparse.Namespace, report: Report, seconds_left: float | None) -> None:
    """Whole-machine throughput of each backend (module docstring, item 4); stops at ``seconds_left``."""
    import multiprocessing

    todo = paths[: args.pool_sequences]
    report.add("", f"## Pool: {len(todo)} sequences, {args.pool_size} processes (1 CPU thread each)", "",
               "| rollouts on | sequences done | wall s | sequences per hour | median s per sequence | SR % | "
               "mean E_t cm | mean E_r deg |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for backend in args.pool_backends.split(","):
        tasks = [(str(p), backend, args.device, args.max_generations) for p in todo]
        t0 = time.perf_counter()
        rows: list[dict[str, Any]] = []
        deadline = None if seconds_left is None else t0 + max(1.0, seconds_left)
        # spawn: a CUDA context does not survive a fork. Leaving the block terminates the pool, so a run out of
        # time stops the sequences still being refined.
        with multiprocessing.get_context("spawn").Pool(args.pool_size) as workers:
            done = workers.imap_unordered(pool_job, tasks)
            try:
                for _ in tasks:
                    left = None if deadline is None else max(0.0, deadline - time.perf_counter())
                    rows.append(done.next(timeout=left))
            except multiprocessing.TimeoutError:
                pass
        wall = time.perf_counter() - t0
        if seconds_left is not None:
            seconds_left -= wall
        if not rows:
            report.add(f"| {backend} | 0 of {len(tasks)} | {wall:.0f} | | | | | |")
            continue
        report.add(f"| {backend} | {len(rows)} of {len(tasks)} | {wall:.0f} | {3600 * len(rows) / wall:.0f} | "
                   f"{statistics.median(r['wall_s'] for r in rows):.1f} | "
                   f"{100 * sum(r['success'] for r in rows) / len(rows):.1f} | "
                   f"{statistics.mean(r['E_t'] for r in rows):.2f} | {statistics.mean(r['E_r'] for r in rows):.2f} |")


def main(argv: list[str] | None = None) -> int:
    from bench.samples.draw import read_sample
    from common.dexycb import shared_data_dir

    args = parse_args(argv)
    data = shared_data_dir()
    if data is None:
        print("bench/gpu_rollout.py: ../shared/data is not present", file=sys.stderr)
        return 2
    parts = args.parts.split(",")
    unknown = set(parts) - {"agreement", "throughput", "refine", "pool"}
    if unknown:
        print(f"bench/gpu_rollout.py: unknown --parts {sorted(unknown)}", file=sys.stderr)
        return 2
    device_name = "none (CPU only)"
    if set(parts) - {"pool"} or "warp" in args.pool_backends.split(","):
        try:
            import warp as wp
        except ImportError:
            print("bench/gpu_rollout.py: needs the optional packages: pip install -e '.[gpu]'", file=sys.stderr)
            return 2
        wp.config.quiet = True
        wp.init()
        device = wp.get_device(args.device)
        device_name = f"`{device}` ({getattr(device, 'name', device)})"
    t_start = time.perf_counter()

    def seconds_left() -> float | None:
        return None if args.deadline_s is None else args.deadline_s - (time.perf_counter() - t_start)

    def out_of_time() -> bool:
        left = seconds_left()
        return left is not None and left <= 0

    names = [name for name, _ in read_sample(ROOT / "bench" / "samples" / f"{args.sample}.txt")]
    paths = [data / "dexycb" / "dev" / n for n in names]
    report = Report(args.out)
    report.add("# MuJoCo Warp rollouts vs the CPU path (issue #19 item 5)", "",
               f"Run {datetime.now(UTC):%Y-%m-%d %H:%M} UTC: Warp device {device_name}, {os.cpu_count()} CPU "
               f"cores ({platform.processor() or '?'}), load average before {os.getloadavg()[0]:.1f}; "
               f"`{' '.join(sys.argv[1:] if argv is None else argv)}`.")
    for part in parts:
        if out_of_time():
            report.add("", f"## {part}: skipped (deadline)")
            continue
        if part == "agreement":
            run_agreement(paths[: args.limit], args, report, out_of_time)
        elif part == "throughput":
            report.add("", "## Throughput")
            throughput(paths[0], args, report)
        elif part == "refine" and args.refine:
            report.add("", "## Refinement with the product's options", "",
                       "| sequence | rollouts on | wall s | rollout s | physics steps | attempts | success | E_t cm | "
                       "E_r deg |", "| --- | --- | ---: | ---: | ---: | ---: | --- | ---: | ---: |")
            for path in paths[: args.refine]:
                if out_of_time():
                    report.add(f"| {path.stem} | skipped: deadline | | | | | | | |")
                    continue
                refine_both(path, args, report)
        elif part == "pool":
            pool(paths, args, report, seconds_left())
    report.add("", f"Total {time.perf_counter() - t_start:.0f} s.")
    return 0


def run_agreement(paths: list[Path], args: argparse.Namespace, report: Report,
                  out_of_time: Any) -> None:
    report.add("", "## Agreement: one population per checked window, CPU float64 vs Warp float32", "",
               "| sequence | window (frames) | object moves (CPU) | object position diff at window end, mm "
               "(median / max) | rotation diff max, deg | Spearman rho of losses | same best |",
               "| --- | --- | --- | --- | --- | --- | --- |")
    rows: list[dict[str, Any]] = []
    for path in paths:
        if out_of_time():
            report.add(f"| {path.stem} | skipped: deadline | | | | | |")
            continue
        rows += agreement(path, args, report)
    if rows:
        rho = [r["rho"] for r in rows if r["rho"] == r["rho"]]
        moving = [r for r in rows if r["touching"]]
        moving_rho = [r["rho"] for r in moving if r["rho"] == r["rho"]]
        report.add("", f"{len(rows)} windows ({len(moving)} where the object moves): median rho "
                   f"{statistics.median(rho) if rho else float('nan'):.3f}, same best candidate in "
                   f"{sum(r['same_best'] for r in rows)}/{len(rows)}; where it moves: median rho "
                   f"{statistics.median(moving_rho) if moving_rho else float('nan'):.3f}, median position diff "
                   f"{statistics.median([r['dpos_mm_median'] for r in moving] or [0.0]):.3f} mm.")


if __name__ == "__main__":
    sys.exit(main())
