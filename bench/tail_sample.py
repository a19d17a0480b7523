"""The bounded tail's saving over whole samples, before and after from one run (issue #53 item 3).

    .venv/bin/python bench/tail_sample.py --run --shard 0/2 &   # two processes, one core each
    .venv/bin/python bench/tail_sample.py --run --shard 1/2
    .venv/bin/python bench/tail_sample.py --report              # writes bench/results/tail_sample.md

Refines every sequence of ``--samples`` (default dev120 and holdout80) with the product's whole plan
(``JobOptions.tail="full"``, one simulation thread) and, where that plan's first attempt failed, once more with the
bounded tail (``tail="bounded"``), on the same machine in the same run; both are cached by ``bench/tail.py``'s
``run_one`` in ``var/bench/tail/``, so an interrupted run resumes. The bounded plan differs from the whole one only
after a failed first attempt whose reasons say no grasp can follow the recording (``worker.refine.outcome.
tail_cut_reason``): where the first attempt succeeds the two plans are the same run, and where the bounded run was not
cut it is the same plan again, so "after" takes the bounded run's figures only where it was cut. ``--report`` prints
p90 and maximum wall time per sequence before and after, with SR, E_t and E_r on the paper's protocol.

The whole run takes longer than a working session, and ``var/`` does not outlive the machine: ``--archive`` copies the
cached rows into ``bench/results/tail_sample_runs.jsonl``, each tagged with the CPU and the code digest it ran with, and
a later ``--run`` skips what is archived, so the run continues on another day; the report names every CPU kind and
day it holds, and each sequence's before and after always come from one machine and one day.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.provenance import cpu_model, numpy_simd  # noqa: E402
from bench.refine import code_digest  # noqa: E402
from bench.samples.draw import read_sample  # noqa: E402
from bench.tail import CACHE, run_one, was_cut  # noqa: E402

SAMPLES = ("dev120", "holdout80")
ARCHIVE = ROOT / "bench" / "results" / "tail_sample_runs.jsonl"


def sample_stems(name: str) -> list[str]:
    return [file.removesuffix(".npz") for file, _ in read_sample(ROOT / "bench" / "samples" / f"{name}.txt")]


def shard(stems: list[str], spec: str) -> list[str]:
    """Every N-th stem from the K-th (``K/N``), so N processes split a sample evenly."""
    k, n = (int(x) for x in spec.split("/"))
    if not 0 <= k < n:
        raise SystemExit(f"--shard {spec}: K must be 0..N-1")
    return stems[k::n]


def run(stems: list[str]) -> None:
    done = archived()
    for i, stem in enumerate(stems, 1):
        if (stem, "full") in done and (done[stem, "full"]["first_attempt_success"] or (stem, "bounded") in done):
            continue
        full = run_one(stem, "full")
        line = f"[{i}/{len(stems)}] {stem} full {full['wall_s']} s, {full['attempts']} attempts"
        if not full["first_attempt_success"]:
            bounded = run_one(stem, "bounded")
            line += f"; bounded {bounded['wall_s']} s, cut: {'yes' if was_cut(bounded) else 'no'}"
        print(line, flush=True)


def archived() -> dict[tuple[str, str], dict[str, Any]]:
    """The archived rows by (sequence, mode)."""
    if not ARCHIVE.exists():
        return {}
    rows = (json.loads(line) for line in ARCHIVE.read_text().splitlines() if line.strip())
    return {(r["sequence"], r["mode"]): r for r in rows}


def archive(stems: list[str], code: str | None = None) -> int:
    """Append the cached rows of ``stems`` not archived yet, tagged with this machine's CPU and ``code`` (the digest
    of ``common/`` and ``worker/`` the rows ran with; None: as they are now), and return how many. The cache is this
    machine's (``var/``)."""
    done = archived()
    tag = {"cpu": f"{cpu_model()} ({numpy_simd()})", "code": code or code_digest()}
    new = []
    for stem in stems:
        for mode in ("full", "bounded"):
            hit = CACHE / f"{stem}.{mode}.json"
            if (stem, mode) not in done and hit.exists():
                new.append({**json.loads(hit.read_text()), **tag})
    with ARCHIVE.open("a") as f:
        f.writelines(json.dumps(r, sort_keys=True) + "\n" for r in new)
    return len(new)


def _row(stem: str, mode: str, archive_rows: dict[tuple[str, str], dict[str, Any]]) -> dict[str, Any] | None:
    """This machine's cached row, else the archived one."""
    hit = CACHE / f"{stem}.{mode}.json"
    if hit.exists():
        row: dict[str, Any] = json.loads(hit.read_text())
        return row
    return archive_rows.get((stem, mode))


def pairs(stems: list[str]) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(before, after) per sequence run: the whole plan, and the bounded run where it was cut, else the same run."""
    out, archive_rows = [], archived()
    for stem in stems:
        full = _row(stem, "full", archive_rows)
        if full is None:
            continue
        bounded = _row(stem, "bounded", archive_rows)
        if not full["first_attempt_success"] and bounded is None:
            continue  # its bounded run is still to come
        out.append((full, bounded if bounded is not None and was_cut(bounded) else full))
    return out


def _figures(rows: list[dict[str, Any]]) -> str:
    wall = np.array([r["wall_s"] for r in rows])
    cpu = np.array([r.get("cpu_s", np.nan) for r in rows])
    return (f"{100 * np.mean([r['success'] for r in rows]):.1f} | {np.mean([r['E_t'] for r in rows]):.3f} | "
            f"{np.mean([r['E_r'] for r in rows]):.3f} | {np.median(wall):.1f} | {np.percentile(wall, 90):.1f} | "
            f"{wall.max():.1f} | {wall.sum():.0f} | {np.percentile(cpu, 90):.1f} | {cpu.max():.1f}")


def _machines(rows: list[dict[str, Any]]) -> list[str]:
    """One line per (CPU, day) the rows ran on, with how many rows; a row still only in the cache ran here."""
    here = f"{cpu_model()} ({numpy_simd()})"
    count: dict[tuple[str, str], int] = {}
    for r in rows:
        key = (r.get("cpu", here), str(r.get("at", "?"))[:10])
        count[key] = count.get(key, 0) + 1
    return [f"* {day}: {n} runs on {cpu}" for (cpu, day), n in sorted(count.items(), key=lambda kv: kv[0][1])]


def report(samples: list[str]) -> str:
    lines = [
        "# The bounded tail over whole samples (bench/tail_sample.py)",
        "",
        f"Generated {datetime.now(UTC):%Y-%m-%d %H:%M} UTC on {platform.machine()} ({os.cpu_count()} cores), one "
        "simulation thread per sequence. Before: the product's whole plan; after: the bounded tail "
        "(`JobOptions.tail=\"bounded\"`), the same run where the plans are the same. Paper's protocol. CPU s is "
        "the process's CPU time, which load from other work on the machine does not inflate.",
        "",
        "| sample | n | plan | cut | SR % | E_t cm | E_r deg | median wall s | p90 wall s | max wall s | sum s | "
        "p90 CPU s | max CPU s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    every: list[tuple[dict[str, Any], dict[str, Any]]] = []
    for name in [*samples, "all"]:
        got = every if name == "all" else pairs(sample_stems(name))
        if name != "all":
            every += got
        if not got:
            continue
        cut = sum(after is not before for before, after in got)
        for plan, rows in (("whole (before)", [b for b, _ in got]), ("bounded (after)", [a for _, a in got])):
            lines.append(f"| {name} | {len(got)} | {plan} | {cut if 'after' in plan else ''} | {_figures(rows)} |")
    runs = [b for b, _ in every] + [a for b, a in every if a is not b]
    if runs:
        lines += ["", "Where the runs were made (each sequence's before and after on one machine, one day):", "",
                  *_machines(runs)]
    cut_rows = [(b, a) for b, a in every if a is not b]
    if cut_rows:
        lines += ["", "Cut sequences (wall s / attempts / E_t cm / E_r deg):", "",
                  "| sequence | whole plan | bounded |", "|---|---|---|"]
        lines += [f"| {b['sequence']} | {b['wall_s']} / {b['attempts']} / {b['E_t']:.2f} / {b['E_r']:.2f} | "
                  f"{a['wall_s']} / {a['attempts']} / {a['E_t']:.2f} / {a['E_r']:.2f} |" for b, a in cut_rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", nargs="*", choices=SAMPLES, default=list(SAMPLES))
    p.add_argument("--run", action="store_true", help="refine what is not cached yet")
    p.add_argument("--shard", default="0/1", help="K/N: this process's share of the sequences (default all)")
    p.add_argument("--archive", action="store_true",
                   help=f"append the cached rows to {ARCHIVE.relative_to(ROOT)}, so another day's run continues them")
    p.add_argument("--code", help="with --archive: the code digest the cached rows ran with, where common/ or worker/ "
                   "changed since the run began (bench/refine.py's code_digest then; default: as they are now)")
    p.add_argument("--report", action="store_true", help="write the before/after table")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "tail_sample.md")
    args = p.parse_args()
    stems = [s for name in args.samples for s in sample_stems(name)]
    if args.run:
        run(shard(stems, args.shard))
    if args.archive:
        print(f"archived {archive(stems, args.code)} rows in {ARCHIVE.relative_to(ROOT)}")
    if args.report:
        text = report(args.samples)
        args.out.write_text(text)
        print(text)


if __name__ == "__main__":
    main()
