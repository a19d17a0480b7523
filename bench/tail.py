"""Failure reasons against the hand-found classes, and the bounded tail's saving (issue #53 items 2-3).

    .venv/bin/python bench/tail.py --run                  # refine the listed failures, the bounded tail on
    .venv/bin/python bench/tail.py --run --first-attempt  # only the first attempt (restarts 0, no polish)
    .venv/bin/python bench/tail.py --report               # write bench/results/tail.md from what was run

Reads the failures ``bench/results/refine_dev120.md`` and ``refine_holdout80.md`` list and the class each was given
by hand there (and in ``reference_jumps*.md``). ``--run`` refines each sequence (``--only`` a few) with the product's
defaults and the bounded tail on (``JobOptions.tail="bounded"``), and caches its outcome, attempts, evaluations and wall
time in ``var/bench/tail/``; ``--first-attempt`` refines only the first attempt, which is the whole plan of a
sequence the tail cuts and otherwise a stand-in for the classification of one it does not (marked so).
``--report`` writes the confusion table (hand-found class against the outcome's most telling reason) and the wall
times: after, as run here; before, the full plan's time from the reports (another run, and for holdout80 before
the rescue on finer parts existed; noted in the file). Nothing is compared across machines as if it were the same.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.reference_jumps import read_sequence_rows  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "dexycb" / "dev"
CACHE = ROOT / "var" / "bench" / "tail"
REPORTS = {"dev120": ROOT / "bench/results/refine_dev120.md", "holdout80": ROOT / "bench/results/refine_holdout80.md"}
#: The failures the reports list, with the class found by hand there (None: the reports name no cause).
HAND_FOUND: dict[str, tuple[str, str | None, str]] = {
    "20200813-subject-02__20200813_150747": ("dev120", "slipped", "mustard bottle, slips in a two-contact pinch"),
    "20200813-subject-02__20200813_155058": ("dev120", "recording_too_fast", "large marker, 95 deg step at 35-36"),
    "20200820-subject-03__20200820_140724": ("dev120", "recording_too_fast", "tuna can, 67 deg step at 32-33"),
    "20200820-subject-03__20200820_140856": ("dev120", "recording_too_fast", "tuna can, 69 deg step at 41-42"),
    "20200903-subject-04__20200903_113424": ("dev120", "recording_too_fast", "large marker, 80 deg step at 59-60"),
    "20200813-subject-02__20200813_154848": ("holdout80", "recording_too_fast", "scissors, 123 deg step at 54-55"),
    "20200813-subject-02__20200813_155129": ("holdout80", "recording_too_fast", "large marker, 65 deg step at 35-36"),
    "20200903-subject-04__20200903_113307": ("holdout80", "recording_too_fast", "large marker, 50 deg step at 67-68"),
    "20200908-subject-05__20200908_150219": ("holdout80", "fingers_through_object",
                                             "pitcher base, fingers through the handle's filled opening"),
    "20200709-subject-01__20200709_150735": ("holdout80", "unsupported_start",
                                             "bowl, leans on something not simulated, dropped"),
    "20200709-subject-01__20200709_150144": ("holdout80", None, "pitcher base, past the limit on some frame"),
    "20200820-subject-03__20200820_141550": ("holdout80", None, "gelatin box, 1.24 cm / 12.7 deg"),
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", action="store_true", help="refine the sequences not yet cached")
    p.add_argument("--first-attempt", action="store_true", help="with --run: the first attempt only")
    p.add_argument("--full-tail", action="store_true", help="with --run: the whole plan (the default tail), for the "
                   "same machine's before")
    p.add_argument("--only", nargs="*", default=None, help="sequence stems (default: every listed failure)")
    p.add_argument("--reclassify", action="store_true", help="classify the cached results again (current code)")
    p.add_argument("--report", action="store_true", help="write bench/results/tail.md")
    p.add_argument("--out", type=Path, default=ROOT / "bench/results/tail.md")
    args = p.parse_args()
    if args.run:
        for stem in args.only or list(HAND_FOUND):
            print(json.dumps(run_one(stem, "first_attempt" if args.first_attempt else
                                     "full" if args.full_tail else "bounded")), flush=True)
    if args.reclassify:
        reclassify()
    if args.report:
        text = report()
        args.out.write_text(text)
        print(text)


def run_one(stem: str, mode: str) -> dict[str, Any]:
    """Refine ``stem`` in ``mode`` (bounded, full, first_attempt; cached per mode) and return its row."""
    hit = CACHE / f"{stem}.{mode}.json"
    if hit.exists():
        cached: dict[str, Any] = json.loads(hit.read_text())
        return cached
    from common.job_options import JobOptions
    from common.sequence_io import load_sequence
    from common.settings import get_settings
    from worker.refine.run import refine_sequence

    options = {"first_attempt": JobOptions(restarts=0, polish=False), "full": JobOptions(tail="full"),
               "bounded": JobOptions(tail="bounded")}[mode]
    seq = load_sequence(DATA / f"{stem}.npz")
    t0, c0 = time.perf_counter(), time.process_time()
    out = refine_sequence(seq, options, cache_dir=get_settings().resolved_cache_dir())
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    s = out.summary
    paper = s["metrics"]["refined"]["paper"]
    # On a machine shared with other work the wall time is mostly waiting: the process's CPU time is what the
    # refinement cost (one thread), comparable with the wall time of the reports' runs on an idle machine.
    row = {"sequence": stem, "mode": mode, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "outcome": s["outcome"],
           "steps": s["timings"]["steps"],
           "attempts": len(s["attempts"]) or 1, "evaluations": s["timings"]["evaluations"],
           "success": paper["success"], "E_t": paper["E_t"], "E_r": paper["E_r"],
           "first_attempt_success": bool(s["attempts"][0]["paper"]["success"]) if s["attempts"] else paper["success"],
           "load_1min": os.getloadavg()[0], "at": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")}
    CACHE.mkdir(parents=True, exist_ok=True)
    (CACHE / f"{stem}.{mode}.npz").write_bytes(out.to_npz_bytes())
    hit.write_text(json.dumps(row, indent=1))
    return row


def was_cut(row: dict[str, Any]) -> bool:
    """Whether a cached run's plan was cut short (its outcome lists ``plan_cut_short``)."""
    return any(r["code"] == "plan_cut_short" for r in row["outcome"]["reasons"])


def reclassify() -> None:
    """Classify every cached result again with the classifier as it is now (``verify``'s derivation, then
    ``worker.refine.outcome``), keeping its plan_cut_short; rewrites the cached outcomes."""
    from common.outcome import ReasonCode
    from common.result_format import read_arrays, read_summary
    from common.settings import get_settings
    from worker.refine.derive import derive_result
    from worker.refine.outcome import classify_outcome, was_rescued
    from worker.refine.result import prepare_from_result

    cache_dir = get_settings().resolved_cache_dir()
    for npz in sorted(CACHE.glob("*.npz")):
        blob = npz.read_bytes()
        summary, arrays = read_summary(blob), read_arrays(blob)
        prep, keyframes = prepare_from_result(blob, cache_dir=cache_dir)
        derived = derive_result(arrays["sequence_npz"].tobytes(), prep.options, prep.scene.config, prep.rotation_pivot,
                                keyframes, cache_dir=cache_dir, mirror_left=prep.mirror_left)
        contact = derived.final.contact_frames
        fresh = classify_outcome(derived.prep, derived.metrics["refined"], derived.final.object_pose,
                                 hand_contact=None if contact is None else contact.hand,
                                 rescued=was_rescued(derived.prep), cache_dir=cache_dir).model_dump(mode="json")
        fresh["reasons"] += [r for r in summary["outcome"]["reasons"] if r["code"] == ReasonCode.PLAN_CUT_SHORT]
        hit = npz.with_suffix(".json")
        row = json.loads(hit.read_text())
        row["outcome"] = fresh
        hit.write_text(json.dumps(row, indent=1))
        print(npz.stem, [r["code"] for r in fresh["reasons"]], flush=True)


MODES = (
    "Mode: `bounded` is the product's defaults with the bounded tail on (`JobOptions.tail`); `first attempt` refines "
    "the first attempt only (restarts 0, no polish): for a sequence the tail cuts it is the bounded plan's whole "
    "result, otherwise its reasons are those of the first attempt's replay, a stand-in for the final result's. Wall "
    "before: the full plan in the report's run (dev120: 2026-12-06 on this VM kind, with the rescue; holdout80: "
    "2026-12-06 on an Intel Xeon before the rescue existed, so a lower bound of today's full plan)."
)


def _cached(stem: str) -> dict[str, Any] | None:
    for mode in ("bounded", "first_attempt"):
        hit = CACHE / f"{stem}.{mode}.json"
        if hit.exists():
            row: dict[str, Any] = json.loads(hit.read_text())
            return row
    return None


def _run_cell(row: dict[str, Any]) -> str:
    return f"{row['cpu_s']} / {row['wall_s']} / {row['attempts']} / {row['E_t']:.2f} / {row['E_r']:.2f}"


def _reason_cell(reason: dict[str, Any] | None) -> str:
    if reason is None:
        return "-"
    value = "" if reason.get("value") is None else f" {reason['value']:g} {reason.get('unit') or ''}".rstrip()
    frame = "" if reason.get("frame") is None else f" @ {reason['frame']}"
    return f"{reason['code']}{frame}{value}"


def report() -> str:
    from common.outcome import FAILURE_CODES

    walls = {name: read_sequence_rows(path) for name, path in REPORTS.items()}
    rows: list[str] = []
    confusion: dict[tuple[str, str], int] = {}
    for stem, (sample, hand, note) in HAND_FOUND.items():
        got = _cached(stem)
        reasons = [] if got is None else got["outcome"]["reasons"]
        failure = [r for r in reasons if r["code"] in FAILURE_CODES]
        primary = failure[0] if failure else None
        cut = got is not None and was_cut(got)
        before = walls[sample].get(stem, {}).get("wall s", "")
        first_hit = CACHE / f"{stem}.first_attempt.json"
        first = json.loads(first_hit.read_text()) if first_hit.exists() and got and got["mode"] != "first_attempt" \
            else None
        first_primary = None if first is None else next(
            (r for r in first["outcome"]["reasons"] if r["code"] in FAILURE_CODES), None)
        key = (hand or "(none found by hand)", primary["code"] if primary else "(not run)")
        confusion[key] = confusion.get(key, 0) + 1
        rows.append(
            f"| {stem} | {sample} | {note} | {hand or '-'} | {_reason_cell(primary)} | "
            f"{'; '.join(_reason_cell(r) for r in failure[1:]) or '-'} | "
            f"{'' if first is None else _reason_cell(first_primary)} | "
            f"{'' if got is None else got['mode'].replace('_', ' ')} | {'yes' if cut else 'no'} | "
            f"{before} | {'' if got is None else got['wall_s']} | {'' if got is None else got.get('cpu_s', '')} | "
            f"{'' if got is None else got['attempts']} |"
        )
    cut_rows = [(float(walls[HAND_FOUND[st][0]][st]["wall s"]), got.get("cpu_s", got["wall_s"])) for st in HAND_FOUND
                if (got := _cached(st)) is not None and got["mode"] == "bounded"
                and was_cut(got)]
    timing = []
    if cut_rows:
        full, cut_short = np.array([b for b, _ in cut_rows]), np.array([a for _, a in cut_rows])
        timing = [
            "## The bounded tail's saving on the sequences it cuts",
            "",
            "| | n | sum s | p90 s | max s |",
            "|---|---|---|---|---|",
            f"| before: full plan (the reports' runs) | {len(full)} | {full.sum():.0f} | "
            f"{np.percentile(full, 90):.0f} | {full.max():.0f} |",
            f"| after: cut after the first attempt (here: CPU s of the run) | {len(cut_short)} | "
            f"{cut_short.sum():.0f} | "
            f"{np.percentile(cut_short, 90):.0f} | {cut_short.max():.0f} |",
            "",
        ]
    same = []
    for stem in HAND_FOUND:
        full_hit, cut_hit = CACHE / f"{stem}.full.json", CACHE / f"{stem}.bounded.json"
        if full_hit.exists() and cut_hit.exists():
            f, c = json.loads(full_hit.read_text()), json.loads(cut_hit.read_text())
            same.append(f"| {stem} | {_run_cell(f)} | {_run_cell(c)} |")
    if same:
        timing += ["The same machine, both ways (CPU s / wall s / attempts / paper E_t cm / E_r deg):", "",
                   "| sequence | full plan | bounded tail |", "|---|---|---|", *same, ""]
    cost = []
    for sample, size in (("dev120", 120), ("holdout80", 80)):
        pairs = [(walls[sample][st], got) for st, (smp, _, _) in HAND_FOUND.items() if smp == sample
                 and (got := _cached(st)) is not None and got["mode"] == "bounded"
                 and was_cut(got)]
        if pairs:
            dt = sum(g["E_t"] - float(r["E_t 10+"]) for r, g in pairs)
            dr = sum(g["E_r"] - float(r["E_r 10+"]) for r, g in pairs)
            cost.append(f"| {sample} | {len(pairs)} of {size} | {dt / len(pairs):+.2f} / {dr / len(pairs):+.2f} | "
                        f"{dt / size:+.3f} / {dr / size:+.3f} |")
    if cost:
        timing += [
            "The cost: a cut result stays a failure (so SR is unchanged) but loses what the rest of the plan gained "
            "on it; paper's protocol, after minus the report's full plan:",
            "",
            "| sample | cut | per cut sequence E_t cm / E_r deg | the sample's mean E_t cm / E_r deg |",
            "|---|---|---|---|",
            *cost,
            "",
        ]
    lines = [
        "# Failure reasons and the bounded tail (bench/tail.py)",
        "",
        f"Generated {datetime.now(UTC):%Y-%m-%d %H:%M} UTC on {platform.machine()} ({os.cpu_count()} cores, "
        "shared with other sessions: load average 4-12 during the runs, so wall times here are 3-7 times "
        "their CPU times).",
        "",
        "## Confusion: hand-found class against the outcome's most telling reason",
        "",
        "| hand-found class | classifier's primary reason | sequences |",
        "|---|---|---|",
        *[f"| {h} | {c} | {n} |" for (h, c), n in sorted(confusion.items())],
        "",
        *timing,
        "## Per sequence",
        "",
        MODES,
        "",
        "| sequence | sample | what the reports say | hand-found | primary reason | further reasons | "
        "first attempt's primary (product parts) | mode | plan cut | wall s before (report) | wall s after (here) | "
        "CPU s after (here) | attempts after |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        *rows,
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
