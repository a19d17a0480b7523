"""Refinement benchmark on real DexYCB sequences: raw replay vs refined (issue #3, "must show").

    .venv/bin/python bench/refine.py --sample dev40 [--limit N] [--threads 2] [--popsize P] [--max-generations G]
    .venv/bin/python bench/refine.py --sample dev120     # the reporting sample (bench/samples/draw.py)

Reads the sample list ``bench/samples/<sample>.txt`` (file names under ../shared/data/dexycb/dev), refines each
sequence with ``worker.refine.run.refine_sequence`` (sequentially; ``--threads`` simulation threads each) and
writes ``bench/results/refine_dev.md`` (``refine_<sample>.md`` for other samples): per-sequence rows and the
aggregate (success rate, first-attempt success, mean E_t, E_r, E_j, E_ft on both protocols — all frames, and the
paper's: frames 10 onward —, penetration and the hand-held share of lifted frames, median wall seconds per
sequence, share of wall time inside simulation, windows skipped) against the issue's targets, split by hand side
and by the awkward classes tagged in the sample list (``# awkward: ...``, see bench/samples/draw.py).
Per-sequence summaries are cached in ``var/bench/refine/`` so an interrupted run resumes (``--fresh`` ignores the
cache); the cache key holds a hash of the ``common``/``worker`` sources, so a run never mixes results of
different code.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import statistics
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.provenance import provenance_line  # noqa: E402

TARGETS = {"SR": 85.0, "E_t": 0.6, "E_r": 2.5, "E_j": 1.3, "E_ft": 1.6, "median_wall_s": 60.0, "sim_share": 85.0}
#: Issue #15's targets on the paper's protocol (frames 10 onward) on dev120; penetration in mm.
TRUST_TARGETS = {"SR": 95.0, "E_t": 0.5, "E_r": 2.0, "E_j": 1.2, "E_ft": 1.5, "pen_mean": 0.5, "pen_max": 2.0}
PAPER = {"SR": 71.7, "E_t": 0.67, "E_r": 2.97, "E_j": 1.55, "E_ft": 1.84, "median_wall_s": 557.0}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sample", default="dev40", help="sample list name in bench/samples (default dev40)")
    p.add_argument("--limit", type=int, default=None, help="only the first N sequences of the sample")
    p.add_argument("--threads", type=int, default=2, help="simulation threads per sequence (default 2)")
    p.add_argument("--popsize", type=int, default=None, help="CMA-ES population (default: the product's)")
    p.add_argument("--max-generations", type=int, default=None, help="CMA-ES generations per window")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--restarts", type=int, default=None,
                   help="further attempts after a failed or poor first one (default: the product's). The first "
                   "leaves the lookahead's rotation error out and runs with --seed; attempt k >= 1 charges it, with "
                   "seed + (k - 1) x 1000003 (worker/refine/run.py attempt_plan)")
    p.add_argument("--no-polish", dest="polish", action="store_false",
                   help="no polish sweep after the attempts (worker/refine/run.py POLISH_OBJECT_ERROR)")
    p.add_argument("--out", type=Path, default=None,
                   help="report file (default bench/results/refine_dev.md for dev40, refine_<sample>.md otherwise)")
    p.add_argument("--fresh", action="store_true", help="ignore cached per-sequence results")
    p.add_argument("--sim", action="append", default=[], metavar="NAME=VALUE",
                   help="a physics setting (worker.simulation.config.SimConfig) other than the product's default, "
                   "for speed/fidelity experiments; repeatable, e.g. --sim noslip_iterations=0 --sim impratio=30")
    p.add_argument("--cma", action="append", default=[], metavar="NAME=VALUE",
                   help="a CMA-ES setting (worker.refine.windowed.CmaSettings) other than the product's, e.g. "
                   "--cma stall_generations=3; repeatable")
    p.add_argument("--weight", action="append", default=[], metavar="NAME=VALUE",
                   help="a loss weight (worker.refine.losses.DEFAULT_WEIGHTS) other than the product's, e.g. "
                   "--weight grasp_reach=1; repeatable")
    p.add_argument("--coacd", action="append", default=[], metavar="NAME=VALUE",
                   help="a convex-decomposition setting (worker.simulation.convex_cache.COACD_PARAMS) other than the "
                   "product's, for collision-geometry experiments, e.g. --coacd threshold=0.04 --coacd "
                   "max_convex_hull=32; repeatable")
    p.add_argument("--as-primitive", action="store_true",
                   help="replace each sequence's mesh by its tightest enclosing box or cylinder "
                   "(bench/primitive_standin.py): the primitive-object path on real motions; the sample must hold "
                   "objects that fit one, e.g. bench/samples/dev120_primitive.txt")
    p.add_argument("--free-wrist-translation", action="store_true",
                   help="also optimise a 3-D wrist translation offset (JobOptions.free_wrist_translation; the "
                   "product's default parameterisation is 10 pose coefficients + wrist rotation)")
    args = p.parse_args(argv)
    args.loss_weights = parse_overrides(args.weight, p, "--weight", weight_defaults())  # floats, as the defaults
    args.sim_overrides = parse_overrides(args.sim, p, "--sim", sim_defaults())
    args.cma_overrides = parse_overrides(args.cma, p, "--cma", cma_defaults())
    args.coacd_overrides = parse_overrides(args.coacd, p, "--coacd", coacd_defaults())
    if args.out is None:
        name = "refine_dev.md" if args.sample == "dev40" else f"refine_{args.sample}.md"
        args.out = ROOT / "bench" / "results" / name
    return args


def sim_defaults() -> dict[str, Any]:
    from worker.simulation.config import SimConfig

    return SimConfig().to_dict()


def weight_defaults() -> dict[str, Any]:
    from worker.refine.losses import DEFAULT_WEIGHTS

    return dict(DEFAULT_WEIGHTS)


def cma_defaults() -> dict[str, Any]:
    import dataclasses

    from worker.refine.windowed import CmaSettings

    return {k: v for k, v in dataclasses.asdict(CmaSettings()).items() if k != "seed"}


def coacd_defaults() -> dict[str, Any]:
    from worker.simulation.convex_cache import COACD_PARAMS

    return dict(COACD_PARAMS)


def apply_coacd_overrides(overrides: dict[str, Any]) -> None:
    """Set the decomposition settings for this process: ``convex_parts`` reads ``COACD_PARAMS`` at each call, and
    its cache key holds them, so parts made with other settings are never read back for these."""
    from worker.simulation.convex_cache import COACD_PARAMS

    COACD_PARAMS.update(overrides)


def polish_line(rows: list[dict[str, Any]]) -> str:
    """How many sequences got a polish sweep (``worker.refine.run.POLISH_OBJECT_ERROR``), how many kept it, and what
    it did to the object errors of those (paper's protocol; the attempt before it against the result)."""
    from worker.refine.run import attempt_rank

    polished = [r for r in rows if any(a.get("polish") for a in r.get("attempts", []))]
    if not polished:
        return "* polish sweeps: none run"
    kept = []
    for r in polished:
        before = max((a for a in r["attempts"] if not a.get("polish")), key=attempt_rank)
        if before["paper"] != {k: r["metrics"]["refined"]["paper"][k] for k in ("success", "E_t", "E_r")}:
            kept.append((r, before))
    if not kept:
        return f"* polish sweeps: run on {len(polished)} of {len(rows)} sequences, kept on none"
    t0, t1 = (statistics.fmean(x) for x in zip(*((b["paper"]["E_t"], r["metrics"]["refined"]["paper"]["E_t"])
                                                  for r, b in kept), strict=True))
    r0, r1 = (statistics.fmean(x) for x in zip(*((b["paper"]["E_r"], r["metrics"]["refined"]["paper"]["E_r"])
                                                  for r, b in kept), strict=True))
    gained = sum(bool(r["metrics"]["refined"]["success"]) and not b["success"] for r, b in kept)
    return (f"* polish sweeps (a poor best attempt's windows run once more, each keyframe seeing the later ones, "
            f"repeated while kept; worker/refine/run.py): run on {len(polished)} of {len(rows)} sequences"
            f"{further_sweeps(polished)}, kept on {len(kept)} (a sweep's replay ranked better); over those, paper's "
            f"protocol: E_t {t0:.2f} -> {t1:.2f} cm, E_r {r0:.2f} -> {r1:.2f} deg, {gained} failure(s) turned "
            f"success")


def rescue_line(rows: list[dict[str, Any]]) -> str:
    """How many sequences the rescue on finer convex parts ran on (``worker.refine.run.RESCUE``), on which it was
    kept, and what it did to their object errors (paper's protocol; the best attempt on the product's parts against
    the result)."""
    from worker.refine.run import attempt_rank
    from worker.simulation.config import CONVEX_DETAILS

    product = CONVEX_DETAILS[0]

    def fine(entry: dict[str, Any]) -> bool:  # an attempt, or a result's config.sim (older ones record none)
        return entry.get("convex_detail", product) != product

    rescued = [r for r in rows if any(fine(a) for a in r.get("attempts", []))]
    if not rescued:
        return "* rescue on finer convex parts (all attempts failed on a decomposed object): none run"
    kept = [r for r in rescued if fine(r["config"]["sim"])]
    pairs = [(max((a for a in r["attempts"] if not fine(a)), key=attempt_rank)["paper"],
              r["metrics"]["refined"]["paper"]) for r in kept]
    change = ""
    if pairs:
        t0, t1, r0, r1 = (statistics.fmean(p[i][k] for p in pairs) for k in ("E_t", "E_r") for i in (0, 1))
        gained = sum(bool(after["success"]) for _, after in pairs)
        change = (f"; over those, paper's protocol: E_t {t0:.2f} -> {t1:.2f} cm, E_r {r0:.2f} -> {r1:.2f} deg, "
                  f"{gained} turned success ({', '.join(r['sequence'] for r in kept)})")
    return (f"* rescue on finer convex parts (every attempt failed on a decomposed object; worker/refine/run.py "
            f"RESCUE): run on {len(rescued)} of {len(rows)} sequences, kept on {len(kept)}{change}")


def further_sweeps(polished: list[dict[str, Any]]) -> str:
    """", a second sweep on N, a third on M" over the sequences that had a first (none when none had more)."""
    counts = [sum(bool(a.get("polish")) for a in r["attempts"]) for r in polished]
    ordinals = ["second", "third", "fourth", "fifth", "sixth", "seventh", "eighth", "ninth", "tenth"]
    names = [ordinals[k - 2] if k - 2 < len(ordinals) else f"{k}th" for k in range(2, max(counts) + 1)]
    parts = [f"{'an' if name[0] in 'ae' else 'a'} {name} on {sum(c >= k for c in counts)}"
             for k, name in enumerate(names, start=2)]
    return "".join(f", {p}" for p in parts)


def restarts_tag(args: argparse.Namespace) -> str:
    """The cache key's part for ``--restarts`` (none for the product's default, so earlier caches stay valid)."""
    restarts = getattr(args, "restarts", None)
    return "" if restarts is None else f"_r{restarts}"


def parse_overrides(pairs: list[str], parser: argparse.ArgumentParser, flag: str, defaults: dict[str, Any]
                    ) -> dict[str, Any]:
    """``NAME=VALUE`` pairs -> field overrides, each value parsed as the field's default's type."""
    out: dict[str, Any] = {}
    for pair in pairs:
        name, sep, text = pair.partition("=")
        if not sep or name not in defaults:
            parser.error(f"{flag} {pair!r}: expected NAME=VALUE with NAME one of {', '.join(sorted(defaults))}")
        default = defaults[name]
        try:
            if isinstance(default, tuple):
                out[name] = tuple(float(v) for v in text.split(","))
            elif isinstance(default, bool):
                out[name] = text.lower() in ("1", "true", "yes")
            else:
                out[name] = type(default)(text)
        except ValueError:
            parser.error(f"{flag} {pair!r}: {text!r} is not a {type(default).__name__}")
    return out


def override_tag(overrides: dict[str, Any]) -> str:
    """The overrides as a short file-name-safe tag ("" for the product's defaults)."""
    return "".join(f"_{k}={','.join(map(str, v)) if isinstance(v, tuple) else v}" for k, v in sorted(overrides.items()))


def run_one(path: Path, args: argparse.Namespace, cache: Path, awkward: list[str] | None = None) -> dict[str, Any]:
    from common.dexycb import load_dexycb_npz
    from common.job_options import JobOptions
    from common.settings import get_settings
    from worker.refine.run import refine_sequence
    from worker.simulation.config import SimConfig

    weights: dict[str, float] = getattr(args, "loss_weights", None) or {}
    as_primitive = bool(getattr(args, "as_primitive", False))
    free_translation = bool(getattr(args, "free_wrist_translation", False))
    key = (f"{path.stem}__p{args.popsize}_g{args.max_generations}_s{args.seed}_t{args.threads}"
           f"{restarts_tag(args)}{override_tag(args.sim_overrides)}{override_tag(args.cma_overrides)}"
           f"{override_tag({f'w-{k}': v for k, v in weights.items()})}"
           f"{override_tag({f'coacd-{k}': v for k, v in getattr(args, 'coacd_overrides', {}).items()})}"
           f"{'_prim' if as_primitive else ''}"
           f"{'_ftrans' if free_translation else ''}{'' if getattr(args, 'polish', True) else '_nopolish'}"
           f"_c{code_digest()}.json")
    hit = cache / key
    if hit.is_file() and not args.fresh:
        out: dict[str, Any] = json.loads(hit.read_text())
        out["awkward"] = awkward or []
        if "table" not in out:  # cached before results recorded their table: the same fit, recomputed
            from worker.simulation.scene import SimConfig
            from worker.simulation.table_fit import fit_table

            out["table"] = fit_table(load_dexycb_npz(path), SimConfig())[1].to_dict()
        return out
    seq = load_dexycb_npz(path)
    if as_primitive:
        from bench.primitive_standin import MAX_VOLUME_RATIO, primitive_sequence

        standin = primitive_sequence(seq)
        if standin is None:
            raise SystemExit(f"{path.name}: {seq.object.name} fits no box or cylinder within {MAX_VOLUME_RATIO} x "
                             "its convex hull's volume (--as-primitive)")
        seq = standin
    options = JobOptions(seed=args.seed, popsize=args.popsize, max_generations=args.max_generations,
                         loss_weights=weights, free_wrist_translation=free_translation,
                         polish=getattr(args, "polish", True),
                         **({} if getattr(args, "restarts", None) is None else {"restarts": args.restarts}))
    t0 = time.perf_counter()
    config = SimConfig(**args.sim_overrides)
    outcome = refine_sequence(seq, options, threads=args.threads, cache_dir=get_settings().resolved_cache_dir(),
                              config=config, cma_overrides=args.cma_overrides)
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


def aggregate(rows: list[dict[str, Any]], which: str, protocol: str = "all") -> dict[str, float]:
    """Means over the sequences of ``metrics[which]`` on one protocol ("all" frames, or the "paper"'s: frames 10
    onward): SR (and the first attempt's, refined only), the errors, penetration (mean of the per-sequence mean
    per-frame maximum; mean and maximum of the sequence maxima, mm) and the hand-held share of lifted frames.
    Figures a summary does not have (older cached results) come out NaN."""
    ms = [r["metrics"][which] if protocol == "all" else r["metrics"][which].get("paper") or {} for r in rows]

    def mean(key: str) -> float:
        vals = [float(m[key]) for m in ms if m.get(key) is not None]
        return statistics.fmean(vals) if vals else float("nan")

    first = [m.get("success_first_attempt") for m in ms]
    pen_max = [float(m["penetration_max_mm"]) for m in ms if m.get("penetration_max_mm") is not None]
    return {
        "SR": 100.0 * sum(bool(m.get("success")) for m in ms) / len(ms) if all("success" in m for m in ms)
        else float("nan"),
        "SR_first": 100.0 * sum(bool(f) for f in first) / len(ms) if all(f is not None for f in first)
        else float("nan"),
        **{k: mean(k) for k in ("E_t", "E_r", "E_j", "E_ft")},
        "pen_mean": mean("penetration_mean_mm"),
        "pen_max_mean": statistics.fmean(pen_max) if pen_max else float("nan"),
        "pen_max_max": max(pen_max) if pen_max else float("nan"),
        "held": 100.0 * mean("hand_only_fraction"),
    }


def metrics_table(rows: list[dict[str, Any]]) -> list[str]:
    """Raw vs refined on both protocols, clearly labelled, with the plausibility figures (issue #15 items 3-4)."""
    lines = [
        "| | protocol | SR % | SR 1st attempt % | E_t cm | E_r deg | E_j cm | E_ft cm | penetration mm (mean per-frame "
        "max) | sequence max mm (mean / worst) | lifted frames hand-held % |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label, which in (("raw replay", "raw"), ("refined", "refined")):
        for protocol, name in (("all", "all frames"), ("paper", "paper: frames 10+")):
            m = aggregate(rows, which, protocol)
            first = "" if which == "raw" else f"{m['SR_first']:.1f}"
            lines.append(
                f"| {label} | {name} | {m['SR']:.1f} | {first} | {m['E_t']:.2f} | {m['E_r']:.2f} | {m['E_j']:.2f} | "
                f"{m['E_ft']:.2f} | {m['pen_mean']:.2f} | {m['pen_max_mean']:.2f} / {m['pen_max_max']:.2f} | "
                f"{m['held']:.0f} |"
            )
    return lines


def _sum(rows: list[dict[str, Any]], key: str) -> float:
    return float(sum(r["timings"].get(key, 0.0) for r in rows))


def held_until_moved_line(rows: list[dict[str, Any]]) -> str:
    """The sequences whose object no table holds as recorded, so it was held until the recording moved it
    (``SimConfig.unsupported_drift``); results made before the hold recorded it say nothing."""
    held = [r for r in rows if r.get("object_hold", {}).get("until_recording_moves")]
    names = ", ".join(f"{r['sequence'].split('__')[-1]} ({r.get('object', '?')})" for r in held)
    return (f"* object held until the recording moved it (no table holds it as recorded: leaning on something not "
            f"simulated; worker/simulation/config.py `unsupported_drift`): {len(held)} of {len(rows)}"
            + (f": {names}" if names else ""))


def render(rows: list[dict[str, Any]], args: argparse.Namespace, n_sample: int) -> str:
    import platform

    walls = [r["timings"]["wall_s"] for r in rows]
    share = 100.0 * sum(r["timings"]["sim_s"] for r in rows) / sum(walls)
    steps_s = sum(r["timings"]["steps"] for r in rows) / sum(r["timings"]["sim_s"] for r in rows)
    windows = sum(r["windows"]["count"] for r in rows)
    skipped = sum(r["windows"]["skipped"] for r in rows)
    escalated = sum(r["windows"].get("escalated", 0) for r in rows)
    stopped = sum(r["windows"].get("stopped_early", 0) for r in rows)
    tilted = [r for r in rows if r.get("table", {}).get("tilt_deg", 0.0) > 0]
    cma = rows[0]["config"]["cma"]
    # A result whose polish sweep was kept records that sweep's settings, which never escalate (None; inf in older
    # caches): the level reported is a first pass's.
    levels = [r["config"]["cma"].get("escalate_loss") for r in rows]
    escalate = next((x for x in levels if x is not None and math.isfinite(x)), None)
    lines = [
        "# Refinement on DexYCB dev (bench/refine.py)",
        "",
        f"Sample `{args.sample}`: {len(rows)} of {n_sample} sequences (bench/samples/{args.sample}.txt), "
        f"{args.threads} simulation threads, popsize {cma['popsize']}, {cma['max_generations']} generations per "
        f"window, seed {args.seed}. Generated on {args.started} UTC. Machine: {os.cpu_count()} cores "
        f"({platform.processor() or platform.machine()}), load average (1 min) before {args.load_before[0]:.2f} / "
        f"after {os.getloadavg()[0]:.2f}, {os.getloadavg()[2]:.2f} over the last 15 min at the end (with "
        f"{args.threads} threads the run's own load is about {args.threads}), "
        f"MuJoCo {rows[0]['versions']['mujoco']}. Physics: "
        + (", ".join(f"`{k}={v}`" for k, v in sorted(args.sim_overrides.items())) or "the product's defaults")
        + "; CMA-ES: "
        + (", ".join(f"`{k}={v}`" for k, v in sorted(args.cma_overrides.items())) or "the product's defaults")
        + ("" if getattr(args, "restarts", None) is None else f"; restarts: {args.restarts}")
        + ("" if getattr(args, "polish", True) else "; **no polish sweep**")
        + ("" if not getattr(args, "loss_weights", None) else "; loss weights: "
           + ", ".join(f"`{k}={v}`" for k, v in sorted(args.loss_weights.items())))
        + ("" if not getattr(args, "coacd_overrides", None) else "; **convex decomposition**: "
           + ", ".join(f"`{k}={v}`" for k, v in sorted(args.coacd_overrides.items())))
        + ("; **objects replaced by their enclosing box or cylinder** (`--as-primitive`, bench/primitive_standin.py)"
           if getattr(args, "as_primitive", False) else "")
        + ("; **free wrist translation** (`--free-wrist-translation`: 16 coordinates per keyframe, not the product's "
           "default)" if getattr(args, "free_wrist_translation", False) else "")
        + ".",
        "",
        args.provenance,
        "",
        *metrics_table(rows),
        *by_side(rows),
        "",
        *group_table(rows),
        "",
        "| targets / paper | SR % | E_t cm | E_r deg | E_j cm | E_ft cm | penetration mm (mean / seq max) |",
        "|---|---|---|---|---|---|---|",
        f"| target, issue #15 (paper's protocol, dev120) | >= {TRUST_TARGETS['SR']:.0f} | <= {TRUST_TARGETS['E_t']} "
        f"| <= {TRUST_TARGETS['E_r']} | <= {TRUST_TARGETS['E_j']} | <= {TRUST_TARGETS['E_ft']} | "
        f"<= {TRUST_TARGETS['pen_mean']} / <= {TRUST_TARGETS['pen_max']} |",
        f"| target, issue #3 (all frames, dev40) | >= {TARGETS['SR']:.0f} | <= {TARGETS['E_t']} | <= "
        f"{TARGETS['E_r']} | <= {TARGETS['E_j']} | <= {TARGETS['E_ft']} | |",
        f"| paper | {PAPER['SR']} | {PAPER['E_t']} | {PAPER['E_r']} | {PAPER['E_j']} | {PAPER['E_ft']} | |",
        "",
        f"* median wall time per sequence: **{statistics.median(walls):.1f} s** (target <= 60 s, paper 557 s); "
        f"min {min(walls):.1f} s, max {max(walls):.1f} s",
        f"* share of wall time inside simulation: **{share:.1f} %** (target >= 85 %); "
        f"{steps_s:.0f} physics steps per second of simulation time with {args.threads} threads",
        f"* windows skipped (no hand-object contact and loss already low): {skipped} of {windows}; windows given a "
        f"second, larger CMA-ES run (best loss still above {'never' if escalate is None else f'{escalate:.0f}'}): "
        f"{escalated} of {windows}; CMA-ES runs stopped early (best loss stalled): {stopped}",
        f"* table laid under the start pose (worker/simulation: table_fit, rest_pose): tilted in {len(tilted)} of "
        f"{len(rows)} sequences (median {statistics.median([r['table']['tilt_deg'] for r in tilted] or [0]):.1f} deg),"
        " level in the rest",
        held_until_moved_line(rows),
        polish_line(rows),
        rescue_line(rows),
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
        "| sequence | object | side | frames | raw ok | raw E_t | refined ok (1st) | E_t | E_r | E_j | E_ft | "
        "E_t 10+ | E_r 10+ | pen mm | pen max | held % | wall s | sim % | skipped | escalated | table tilt deg | "
        "awkward |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        a, b, t = r["metrics"]["raw"], r["metrics"]["refined"], r["timings"]
        p = b.get("paper") or {}
        first = {True: " (yes)", False: " (no)", None: ""}[b.get("success_first_attempt")]
        lines.append(
            f"| {r['sequence']} | {r['object']} | {r['side']} | {r['frames']} | {'yes' if a['success'] else 'no'} "
            f"| {a['E_t']:.2f} | {'yes' if b['success'] else 'no'}{first} | {b['E_t']:.2f} | {b['E_r']:.2f} | "
            f"{b['E_j']:.2f} | {b['E_ft']:.2f} | {_f(p.get('E_t'))} | {_f(p.get('E_r'))} | "
            f"{_f(b.get('penetration_mean_mm'))} | {_f(b.get('penetration_max_mm'))} | "
            f"{_f(None if b.get('hand_only_fraction') is None else 100 * b['hand_only_fraction'], 0)} | "
            f"{t['wall_s']:.1f} | {100 * t['sim_share']:.0f} | "
            f"{r['windows']['skipped']}/{r['windows']['count']} | {r['windows'].get('escalated', 0)} | "
            f"{r.get('table', {}).get('tilt_deg', float('nan')):.1f} | {','.join(r.get('awkward', []))} |"
        )
    return "\n".join(lines) + "\n"


def groups(rows: list[dict[str, Any]]) -> list[tuple[str, list[dict[str, Any]]]]:
    """The report's splits: by hand side, each awkward class (``bench/samples/draw.py``), and the rest."""
    from bench.samples.draw import AWKWARD

    out = [("all", rows), *((f"{s} hands", [r for r in rows if r["side"] == s]) for s in ("right", "left"))]
    out += [(f"awkward: {c}", [r for r in rows if c in r.get("awkward", [])]) for c in AWKWARD]
    out.append(("not awkward", [r for r in rows if not r.get("awkward")]))
    return [(label, members) for label, members in out if members]


def group_table(rows: list[dict[str, Any]]) -> list[str]:
    """One line per ``groups`` split: raw and refined success (final and first attempt), object errors on both
    protocols, hand errors and median wall time, so the awkward sequences are reported separately."""
    lines = [
        "| group | n | raw SR % | SR % | SR 1st % | E_t cm | E_r deg | E_t 10+ | E_r 10+ | E_j cm | E_ft cm | "
        "median wall s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label, members in groups(rows):
        raw, ref = aggregate(members, "raw"), aggregate(members, "refined")
        paper = aggregate(members, "refined", "paper")
        wall = statistics.median(r["timings"]["wall_s"] for r in members)
        lines.append(
            f"| {label} | {len(members)} | {raw['SR']:.1f} | {ref['SR']:.1f} | {ref['SR_first']:.1f} | "
            f"{ref['E_t']:.2f} | {ref['E_r']:.2f} | {paper['E_t']:.2f} | {paper['E_r']:.2f} | {ref['E_j']:.2f} | "
            f"{ref['E_ft']:.2f} | {wall:.1f} |"
        )
    return lines


def by_side(rows: list[dict[str, Any]]) -> list[str]:
    """The same table for each hand side (left hands failed more often on outside data; issue #15); nothing when
    the rows have one side only."""
    sides = sorted({str(r.get("side")) for r in rows})
    out: list[str] = []
    for side in sides if len(sides) > 1 else []:
        some = [r for r in rows if str(r.get("side")) == side]
        out += ["", f"{side} hands ({len(some)} sequences):", "", *metrics_table(some)]
    return out


def _f(v: Any, digits: int = 2) -> str:
    return "-" if v is None else f"{float(v):.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    from bench.samples.draw import read_sample
    from common.dexycb import shared_data_dir

    args = parse_args(argv)
    apply_coacd_overrides(args.coacd_overrides)
    data = shared_data_dir()
    if data is None:
        print("bench/refine.py: ../shared/data is not present", file=sys.stderr)
        return 2
    sample = read_sample(ROOT / "bench" / "samples" / f"{args.sample}.txt")
    names = [name for name, _ in sample]
    todo = sample[: args.limit] if args.limit else sample
    cache = ROOT / "var" / "bench" / "refine"
    args.started = datetime.now(UTC).strftime("%Y-%m-%d %H:%M")
    args.load_before = os.getloadavg()
    # Stated at the start: a commit made while the run goes on must not be credited with its figures.
    args.provenance = provenance_line(code_digest())
    rows = []
    for i, (name, awkward) in enumerate(todo, 1):
        row = run_one(data / "dexycb" / "dev" / name, args, cache, awkward)
        rows.append(row)
        m, t = row["metrics"], row["timings"]
        print(f"[{i}/{len(todo)}] {name}: raw {'ok' if m['raw']['success'] else 'FAIL'} E_t {m['raw']['E_t']:.2f} "
              f"-> refined {'ok' if m['refined']['success'] else 'FAIL'} E_t {m['refined']['E_t']:.2f} "
              f"E_r {m['refined']['E_r']:.2f} (frames 10+: E_t {_f(m['refined'].get('paper', {}).get('E_t'))} "
              f"E_r {_f(m['refined'].get('paper', {}).get('E_r'))}) penetration "
              f"{_f(m['refined'].get('penetration_mean_mm'))}/{_f(m['refined'].get('penetration_max_mm'))} mm  "
              f"{t['wall_s']:.1f}s", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(render(rows, args, len(names)))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
