"""Refinement benchmark on real DexYCB sequences: raw replay vs refined (issue #3, "must show").

    .venv/bin/python bench/refine.py --sample dev40 [--limit N] [--threads 2] [--popsize P] [--max-generations G]
    .venv/bin/python bench/refine.py --sample dev120     # the reporting sample (bench/samples/draw.py)

Reads the sample list ``bench/samples/<sample>.txt`` (file names under ../shared/data/dexycb/dev), refines each
sequence with ``worker.refine.run.refine_sequence`` (sequentially; ``--threads`` simulation threads each) and
writes ``bench/results/refine_dev.md`` (``refine_<sample>.md`` for other samples): per-sequence rows and the
aggregate (success rate, mean E_t, E_r, E_j, E_ft, median wall seconds per sequence, share of wall time inside
simulation, windows skipped) against the issue's targets, split by hand side and by the awkward classes tagged in
the sample list (``# awkward: ...``, see bench/samples/draw.py). Per-sequence summaries are cached in
``var/bench/refine/`` so an interrupted run resumes (``--fresh`` ignores the cache); the cache key holds a hash of
the ``common``/``worker`` sources, so a run never mixes results of different code.
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TARGETS = {"SR": 85.0, "E_t": 0.6, "E_r": 2.5, "E_j": 1.3, "E_ft": 1.6, "median_wall_s": 60.0, "sim_share": 85.0}
PAPER = {"SR": 71.7, "E_t": 0.67, "E_r": 2.97, "E_j": 1.55, "E_ft": 1.84, "median_wall_s": 557.0}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sample", default="dev40", help="sample list name in bench/samples (default dev40)")
    p.add_argument("--limit", type=int, default=None, help="only the first N sequences of the sample")
    p.add_argument("--threads", type=int, default=2, help="simulation threads per sequence (default 2)")
    p.add_argument("--popsize", type=int, default=None, help="CMA-ES population (default: the product's)")
    p.add_argument("--max-generations", type=int, default=None, help="CMA-ES generations per window")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=None,
                   help="report file (default bench/results/refine_dev.md for dev40, refine_<sample>.md otherwise)")
    p.add_argument("--fresh", action="store_true", help="ignore cached per-sequence results")
    args = p.parse_args(argv)
    if args.out is None:
        name = "refine_dev.md" if args.sample == "dev40" else f"refine_{args.sample}.md"
        args.out = ROOT / "bench" / "results" / name
    return args


def run_one(path: Path, args: argparse.Namespace, cache: Path, awkward: list[str] | None = None) -> dict[str, Any]:
    from common.dexycb import load_dexycb_npz
    from common.job_options import JobOptions
    from worker.refine.run import refine_sequence

    key = f"{path.stem}__p{args.popsize}_g{args.max_generations}_s{args.seed}_t{args.threads}_c{code_digest()}.json"
    hit = cache / key
    if hit.is_file() and not args.fresh:
        out: dict[str, Any] = json.loads(hit.read_text())
        out["awkward"] = awkward or []
        if "table" not in out:  # cached before results recorded their table: the same fit, recomputed
            from worker.scene import SimConfig
            from worker.table_fit import fit_table

            out["table"] = fit_table(load_dexycb_npz(path), SimConfig())[1].to_dict()
        return out
    seq = load_dexycb_npz(path)
    options = JobOptions(seed=args.seed, popsize=args.popsize, max_generations=args.max_generations)
    t0 = time.perf_counter()
    outcome = refine_sequence(seq, options, threads=args.threads)
    summary = dict(outcome.summary)
    summary["bench_wall_s"] = time.perf_counter() - t0
    summary["object"] = seq.object.name
    summary["side"] = seq.hands[0].side
    cache.mkdir(parents=True, exist_ok=True)
    hit.write_text(json.dumps(summary))
    summary["awkward"] = awkward or []
    return summary


@functools.cache
def code_digest() -> str:
    """A short hash of the Python sources of ``common`` and ``worker``: part of the cache key, so a resumed run
    never mixes per-sequence results of different code into one table."""
    import hashlib

    h = hashlib.sha256()
    for path in sorted(p for pkg in ("common", "worker") for p in (ROOT / pkg).rglob("*.py")):
        h.update(path.relative_to(ROOT).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


def aggregate(rows: list[dict[str, Any]], which: str) -> dict[str, float]:
    ms = [r["metrics"][which] for r in rows]
    return {
        "SR": 100.0 * sum(bool(m["success"]) for m in ms) / len(ms),
        **{k: statistics.fmean(float(m[k]) for m in ms) for k in ("E_t", "E_r", "E_j", "E_ft")},
    }


def groups(rows: list[dict[str, Any]]) -> list[tuple[str, list[dict[str, Any]]]]:
    """The report's splits: by hand side, each awkward class (``bench/samples/draw.py``), and the rest."""
    from bench.samples.draw import AWKWARD

    out = [("all", rows), *((f"{s} hands", [r for r in rows if r["side"] == s]) for s in ("right", "left"))]
    out += [(f"awkward: {c}", [r for r in rows if c in r.get("awkward", [])]) for c in AWKWARD]
    out.append(("not awkward", [r for r in rows if not r.get("awkward")]))
    return [(label, members) for label, members in out if members]


def group_table(rows: list[dict[str, Any]]) -> list[str]:
    """Markdown rows: raw and refined success and errors, and median wall time, per ``groups`` split."""
    lines = [
        "| group | n | raw SR % | raw E_t | SR % | E_t cm | E_r deg | E_j cm | E_ft cm | median wall s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label, members in groups(rows):
        raw, ref = aggregate(members, "raw"), aggregate(members, "refined")
        wall = statistics.median(r["timings"]["wall_s"] for r in members)
        lines.append(
            f"| {label} | {len(members)} | {raw['SR']:.1f} | {raw['E_t']:.2f} | {ref['SR']:.1f} | {ref['E_t']:.2f} | "
            f"{ref['E_r']:.2f} | {ref['E_j']:.2f} | {ref['E_ft']:.2f} | {wall:.1f} |"
        )
    return lines


def _sum(rows: list[dict[str, Any]], key: str) -> float:
    return float(sum(r["timings"].get(key, 0.0) for r in rows))


def render(rows: list[dict[str, Any]], args: argparse.Namespace, n_sample: int) -> str:
    import os
    import platform

    raw, ref = aggregate(rows, "raw"), aggregate(rows, "refined")
    walls = [r["timings"]["wall_s"] for r in rows]
    share = 100.0 * sum(r["timings"]["sim_s"] for r in rows) / sum(walls)
    steps_s = sum(r["timings"]["steps"] for r in rows) / sum(r["timings"]["sim_s"] for r in rows)
    windows = sum(r["windows"]["count"] for r in rows)
    skipped = sum(r["windows"]["skipped"] for r in rows)
    escalated = sum(r["windows"].get("escalated", 0) for r in rows)
    tilted = [r for r in rows if r.get("table", {}).get("tilt_deg", 0.0) > 0]
    cma = rows[0]["config"]["cma"]
    lines = [
        "# Refinement on DexYCB dev (bench/refine.py)",
        "",
        f"Sample `{args.sample}`: {len(rows)} of {n_sample} sequences (bench/samples/{args.sample}.txt), "
        f"{args.threads} simulation threads, popsize {cma['popsize']}, {cma['max_generations']} generations per "
        f"window, seed {args.seed}. Machine: {os.cpu_count()} cores shared with other work "
        f"({platform.processor() or platform.machine()}), MuJoCo {rows[0]['versions']['mujoco']}.",
        "",
        "| | SR % | E_t cm | E_r deg | E_j cm | E_ft cm |",
        "|---|---|---|---|---|---|",
        *(
            f"| {label} | {m['SR']:.1f} | {m['E_t']:.2f} | {m['E_r']:.2f} | {m['E_j']:.2f} | {m['E_ft']:.2f} |"
            for label, m in (("raw replay", raw), ("refined", ref))
        ),
        f"| target | >= {TARGETS['SR']:.0f} | <= {TARGETS['E_t']} | <= {TARGETS['E_r']} | <= {TARGETS['E_j']} | "
        f"<= {TARGETS['E_ft']} |",
        f"| paper | {PAPER['SR']} | {PAPER['E_t']} | {PAPER['E_r']} | {PAPER['E_j']} | {PAPER['E_ft']} |",
        "",
        *group_table(rows),
        "",
        f"* median wall time per sequence: **{statistics.median(walls):.1f} s** (target <= 60 s, paper 557 s); "
        f"min {min(walls):.1f} s, max {max(walls):.1f} s",
        f"* share of wall time inside simulation: **{share:.1f} %** (target >= 85 %); "
        f"{steps_s:.0f} physics steps per second of simulation time with {args.threads} threads",
        f"* windows skipped (no hand-object contact and loss already low): {skipped} of {windows}; windows given a "
        f"second, larger CMA-ES run (best loss still above {cma.get('escalate_loss', float('inf')):.0f}): "
        f"{escalated} of {windows}",
        f"* table laid under the start pose (worker/table_fit.py, worker/rest_pose.py): tilted in {len(tilted)} of "
        f"{len(rows)} sequences (median {statistics.median([r['table']['tilt_deg'] for r in tilted] or [0]):.1f} deg),"
        " level in the rest",
        f"* where the time goes (sums over the sequences): batched CMA-ES rollouts {_sum(rows, 'rollout_s'):.0f} s "
        f"({_sum(rows, 'rollout_steps') / max(_sum(rows, 'rollout_s'), 1e-9):.0f} steps/s), Python-stepped "
        f"probes, commits and replays {_sum(rows, 'python_step_s'):.0f} s "
        f"({_sum(rows, 'python_steps') / max(_sum(rows, 'python_step_s'), 1e-9):.0f} steps/s), retargeting and "
        f"scene compilation {_sum(rows, 'prepare_s'):.0f} s, the rest (CMA-ES, losses, I/O) "
        f"{sum(walls) - _sum(rows, 'rollout_s') - _sum(rows, 'python_step_s') - _sum(rows, 'prepare_s'):.0f} s "
        f"of {sum(walls):.0f} s",
        "",
        "## Per sequence",
        "",
        "| sequence | object | side | frames | raw ok | raw E_t | refined ok | E_t | E_r | E_j | E_ft | wall s | sim % "
        "| skipped | escalated | table tilt deg | awkward |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        a, b, t = r["metrics"]["raw"], r["metrics"]["refined"], r["timings"]
        lines.append(
            f"| {r['sequence']} | {r['object']} | {r['side']} | {r['frames']} | {'yes' if a['success'] else 'no'} "
            f"| {a['E_t']:.2f} | {'yes' if b['success'] else 'no'} | {b['E_t']:.2f} | {b['E_r']:.2f} | "
            f"{b['E_j']:.2f} | {b['E_ft']:.2f} | {t['wall_s']:.1f} | {100 * t['sim_share']:.0f} | "
            f"{r['windows']['skipped']}/{r['windows']['count']} | {r['windows'].get('escalated', 0)} | "
            f"{r.get('table', {}).get('tilt_deg', float('nan')):.1f} | {','.join(r.get('awkward', []))} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from bench.samples.draw import read_sample
    from common.dexycb import shared_data_dir

    args = parse_args(argv)
    data = shared_data_dir()
    if data is None:
        print("bench/refine.py: ../shared/data is not present", file=sys.stderr)
        return 2
    sample = read_sample(ROOT / "bench" / "samples" / f"{args.sample}.txt")
    names = [name for name, _ in sample]
    todo = sample[: args.limit] if args.limit else sample
    cache = ROOT / "var" / "bench" / "refine"
    rows = []
    for i, (name, awkward) in enumerate(todo, 1):
        row = run_one(data / "dexycb" / "dev" / name, args, cache, awkward)
        rows.append(row)
        m, t = row["metrics"], row["timings"]
        print(f"[{i}/{len(todo)}] {name}: raw {'ok' if m['raw']['success'] else 'FAIL'} E_t {m['raw']['E_t']:.2f} "
              f"-> refined {'ok' if m['refined']['success'] else 'FAIL'} E_t {m['refined']['E_t']:.2f} "
              f"E_r {m['refined']['E_r']:.2f}  {t['wall_s']:.1f}s", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(render(rows, args, len(names)))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
