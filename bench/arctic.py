"""Two hands and articulated objects on real ARCTIC recordings: raw replay vs refined (issue #52, "must show").

    .venv/bin/python bench/arctic.py --arctic DIR [--two-hands per_hand|joint] [--threads 2] [--only NAME ...]
        [--restarts N] [--no-polish] [--seed N]

``DIR`` is the ``assets/arctic`` folder of the dexmachina repository (its ``processed/<subject>/*.npy`` and one
folder per object with the URDF and meshes); the ARCTIC licence forbids redistribution, so nothing of it is ever
copied into this project. Every sequence whose object has its URDF is refined (sequentially, ``--threads``
simulation threads each) and ``bench/results/refine_arctic.md`` is written (``--out``): per sequence and as means,
raw replay vs refined, on both protocols — success, E_t, E_r, E_a, E_j and E_ft per hand, penetration (mean
per-frame maximum and sequence maximum) —, wall time and physics steps per second on this machine. Per-sequence
summaries are cached in ``var/bench/arctic/<mode>/`` (keyed by a hash of the ``common``/``worker`` sources) so an
interrupted run resumes; ``--compare`` renders the per-hand vs joint comparison from both modes' caches.
``--restarts 0 --no-polish`` is one attempt alone; ``--restarts 0`` is one attempt and its polish sweeps (each a
whole run here). The local repair (``worker.refine.repair``) runs in their place only with
the job option ``local_repair`` on (``--local-repair``; off by default).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.provenance import KERNELS, numpy_simd, provenance_line  # noqa: E402
from bench.refine import cma_defaults, code_digest, override_tag, parse_overrides  # noqa: E402

#: The issue's goals (paper's protocol): most sequences succeed, E_t <= 1 cm, E_r <= 5 deg, E_a <= 5 deg,
#: sequence maximum penetration <= 2 mm, at most 15 min per sequence on 2 threads.
GOALS = {"E_t": 1.0, "E_r": 5.0, "E_a": 5.0, "pen_max": 2.0, "wall_s": 900.0}


def plan_key(args: argparse.Namespace) -> str:
    """The part of the cache key that says which plan ran (restarts, polish, repair, forced kernels, seed, CMA-ES
    overrides), so runs of other plans do not answer for each other."""
    kernels = "" if args.kernels == "original" else f"_k{args.kernels}"
    seed = f"_s{args.seed}" if args.seed else ""
    return (f"_r{args.restarts}_p{int(args.polish)}_l{int(args.local_repair)}{kernels}{seed}"
            f"{override_tag(args.cma_overrides)}")


def result_name(sequence: str, two_hands: str, seed: int = 0) -> str:
    """The stored result's file name for ``sequence`` ("s01/mixer_use_01"); another seed's draw gets its own."""
    return f"{sequence.replace('/', '_')}_{two_hands}{f'_s{seed}' if seed else ''}.result.npz"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--arctic", type=Path, required=True,
                   help="dexmachina's assets/arctic folder (processed/<subject>/*.npy and one folder per object)")
    p.add_argument("--two-hands", choices=("per_hand", "joint"), default="per_hand",
                   help="one CMA-ES per hand (the published method) or one over both hands' keyframes")
    p.add_argument("--threads", type=int, default=2, help="simulation threads per sequence (default 2)")
    p.add_argument("--restarts", type=int, default=None, help="further attempts (default: the product's)")
    p.add_argument("--no-polish", dest="polish", action="store_false", help="no polish sweeps")
    p.add_argument("--local-repair", action="store_true",
                   help="polish a failed attempt by the local repair instead of the sweeps (job option local_repair)")
    p.add_argument("--only", nargs="*", default=None, help="only these sequences (file stems)")
    p.add_argument("--seed", type=int, default=0,
                   help="the job's CMA-ES seed (JobOptions.seed, default 0): another draw of the same plan, to see how "
                        "much a sequence's figures vary between draws")
    p.add_argument("--kernels", choices=tuple(KERNELS), default="original",
                   help="NumPy's and OpenBLAS's kernels: this host's own (original), or those of a host without "
                        "AVX-512 (avx2) or without AVX2 (sse). These long two-hand refinements follow the last bits, "
                        "so rows compare across machines only under the same kernels; avx2 runs on every x86 host "
                        "these figures came from")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "refine_arctic.md")
    p.add_argument("--results", type=Path, default=ROOT / "var" / "arctic",
                   help="where the result files are written (outside the repository's tracked files)")
    p.add_argument("--cma", action="append", default=[], metavar="NAME=VALUE",
                   help="a CMA-ES setting (worker.refine.windowed.CmaSettings) other than the product's, e.g. "
                   "--cma rewind_windows=3; repeatable")
    p.add_argument("--fresh", action="store_true", help="ignore cached per-sequence results")
    p.add_argument("--compare", action="store_true",
                   help="render the report from both modes' cached rows (per-hand vs joint), running nothing")
    args = p.parse_args(argv)
    args.cma_overrides = parse_overrides(args.cma, p, "--cma", cma_defaults())
    return args


def usable_sequences(arctic: Path) -> list[Path]:
    """Every processed sequence whose object folder holds its URDF (the snapshot lacks some files)."""
    from common.arctic import object_name_of

    out = []
    for path in sorted((arctic / "processed").glob("*/*.npy")):
        name = object_name_of(path)
        if (arctic / name / f"{name}.urdf").is_file():
            out.append(path)
    return out


def _metrics(m: dict[str, Any]) -> dict[str, Any]:
    """The figures a row keeps of one replay's metrics, both protocols."""
    out: dict[str, Any] = {}
    for proto, block in (("all", m), ("paper", m["paper"])):
        row = {k: block.get(k) for k in ("success", "E_t", "E_r", "E_a", "max_E_a", "E_j", "E_ft", "max_E_t",
                                          "max_E_r", "penetration_mean_mm", "penetration_max_mm")}
        row["per_hand"] = block.get("per_hand", {})
        out[proto] = row
    return out


def run_one(path: Path, args: argparse.Namespace, cache: Path) -> dict[str, Any]:
    from common.job_options import JobOptions
    from common.sequence_io import load_sequence
    from worker.refine.run import refine_sequence

    key = cache / f"{path.parent.name}_{path.stem}.json"
    if key.is_file() and not args.fresh:
        return dict(json.loads(key.read_text()))
    seq = load_sequence(path)
    options = JobOptions(two_hands=args.two_hands, polish=args.polish, local_repair=args.local_repair,
                         seed=args.seed, **({} if args.restarts is None else {"restarts": args.restarts}))
    t0 = time.perf_counter()
    last = [t0]

    def progress(p: Any) -> None:
        now = time.perf_counter()
        if now - last[0] >= 60:
            last[0] = now
            print(f"  {now - t0:5.0f} s  attempt {p.attempt}  window {p.window}/{p.windows}", flush=True)

    out = refine_sequence(seq, options, threads=args.threads, progress=progress, cache_dir=ROOT / "var" / "cache",
                          cma_overrides=args.cma_overrides)  # fmt: skip
    wall = time.perf_counter() - t0
    args.results.mkdir(parents=True, exist_ok=True)
    result = args.results / result_name(f"{path.parent.name}/{path.stem}", args.two_hands, args.seed)
    result.write_bytes(out.to_npz_bytes())
    s = out.summary
    t = s["timings"]
    row = {
        "sequence": f"{path.parent.name}/{path.stem}", "object": seq.object.name, "frames": seq.num_frames,
        "raw": _metrics(s["metrics"]["raw"]), "refined": _metrics(s["metrics"]["refined"]),
        "wall_s": wall, "steps": t.get("steps"), "steps_per_second": t.get("steps_per_second"),
        "attempts": len(s.get("attempts", [])) or 1, "two_hands": args.two_hands,
        # The process's peak resident memory so far (it only grows): what a long sequence costs in memory.
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }  # fmt: skip
    cache.mkdir(parents=True, exist_ok=True)
    key.write_text(json.dumps(row))
    return row


def _f(v: Any, digits: int = 2) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    return f"{v:.{digits}f}"


def _mean(rows: list[dict[str, Any]], which: str, proto: str, key: str) -> float | None:
    vals = [r[which][proto][key] for r in rows if r[which][proto].get(key) is not None]
    return statistics.fmean(float(v) for v in vals) if vals else None


def _hand(r: dict[str, Any], which: str, proto: str, side: str, key: str) -> Any:
    return r[which][proto].get("per_hand", {}).get(side, {}).get(key)


def table(rows: list[dict[str, Any]], proto: str) -> list[str]:
    head = ("| sequence | frames | | success | E_t cm | E_r deg | E_a deg | E_j R / L cm | E_ft R / L cm | "
            "pen mean / max mm | wall s (peak RSS) | steps/s |")
    lines = [head, "|" + "---|" * 12]
    for r in rows:
        for which in ("raw", "refined"):
            m = r[which][proto]
            hands = " / ".join(_f(_hand(r, which, proto, s, "E_j")) for s in ("right", "left"))
            tips = " / ".join(_f(_hand(r, which, proto, s, "E_ft")) for s in ("right", "left"))
            wall = f"{r['wall_s']:.0f} ({r.get('peak_rss_mib', 0):.0f} MiB)" if which == "refined" else ""
            sps = _f(r["steps_per_second"], 0) if which == "refined" else ""
            lines.append(f"| {r['sequence'] if which == 'raw' else ''} | {r['frames'] if which == 'raw' else ''} | "
                         f"{which} | {_f(m['success'])} | {_f(m['E_t'])} | {_f(m['E_r'])} | {_f(m['E_a'])} | {hands} | "
                         f"{tips} | {_f(m['penetration_mean_mm'])} / {_f(m['penetration_max_mm'])} | {wall} | {sps} |")
    for which in ("raw", "refined"):
        n = sum(bool(r[which][proto]["success"]) for r in rows)
        lines.append(
            f"| **mean** | | {which} | {n}/{len(rows)} | {_f(_mean(rows, which, proto, 'E_t'))} | "
            f"{_f(_mean(rows, which, proto, 'E_r'))} | {_f(_mean(rows, which, proto, 'E_a'))} | "
            f"{_f(_mean(rows, which, proto, 'E_j'))} (both) | {_f(_mean(rows, which, proto, 'E_ft'))} (both) | "
            f"{_f(_mean(rows, which, proto, 'penetration_mean_mm'))} / "
            f"{_f(_mean(rows, which, proto, 'penetration_max_mm'))} | "
            f"{_f(statistics.median(r['wall_s'] for r in rows), 0) if which == 'refined' else ''} | |")
    return lines


def first_failure(result: Path) -> tuple[int | None, str]:
    """The first frame (paper's protocol) past a success limit in a stored result (None: none, or no result), and
    a line saying which limit and by how much ("-" without a result, "none" where no frame is past a limit)."""
    if not result.is_file():
        return None, "-"
    from common.result_format import read_arrays
    from worker.simulation.metrics import PAPER_FIRST_FRAME, SUCCESS_POSITION_CM, SUCCESS_ROTATION_DEG

    a = read_arrays(result.read_bytes())
    e_t, e_r = a["metrics_refined_e_t_cm"], a["metrics_refined_e_r_deg"]
    e_a = a.get("metrics_refined_e_a")
    ok_a = a.get("metrics_refined_a_ok")
    for f in range(PAPER_FIRST_FRAME, len(e_t)):
        past = []
        if e_t[f] > SUCCESS_POSITION_CM:
            past.append(f"E_t {e_t[f]:.1f} cm")
        if e_r[f] > SUCCESS_ROTATION_DEG:
            past.append(f"E_r {e_r[f]:.0f} deg")
        if ok_a is not None and e_a is not None and ok_a[f] == 0:
            past.append(f"E_a {e_a[f]:.0f} deg")
        if past:
            bad = np.flatnonzero((e_t[PAPER_FIRST_FRAME:] > SUCCESS_POSITION_CM)
                                 | (e_r[PAPER_FIRST_FRAME:] > SUCCESS_ROTATION_DEG)
                                 | (np.zeros_like(e_t[PAPER_FIRST_FRAME:], dtype=bool) if ok_a is None
                                    else ok_a[PAPER_FIRST_FRAME:] == 0))  # fmt: skip
            return f, f"frame {f}: {', '.join(past)} ({bad.size} frames past a limit)"
    return None, "none"


def failures(rows: list[dict[str, Any]], args: argparse.Namespace) -> list[str]:
    lines = ["| sequence | first frame past a limit (refined, paper's protocol) |", "|---|---|"]
    for r in rows:
        result = args.results / result_name(r["sequence"], r["two_hands"], args.seed)
        lines.append(f"| {r['sequence']} | {first_failure(result)[1]} |")
    return lines


def comparison(by_mode: dict[str, list[dict[str, Any]]]) -> list[str]:
    """Per-hand vs joint CMA-ES on the sequences both ran (paper's protocol)."""
    names = sorted(set.intersection(*(set(r["sequence"] for r in rows) for rows in by_mode.values())))
    lines = ["| sequence | mode | success | E_t cm | E_r deg | E_a deg | E_j cm | pen max mm | wall s |",
             "|" + "---|" * 9]
    for name in names:
        for mode, rows in by_mode.items():
            r = next(x for x in rows if x["sequence"] == name)
            m = r["refined"]["paper"]
            lines.append(f"| {name} | {mode} | {_f(m['success'])} | {_f(m['E_t'])} | {_f(m['E_r'])} | {_f(m['E_a'])} "
                         f"| {_f(m['E_j'])} | {_f(m['penetration_max_mm'])} | {_f(r['wall_s'], 0)} |")
    for mode, rows in by_mode.items():
        sel = [r for r in rows if r["sequence"] in names]
        if sel:
            n = sum(bool(r["refined"]["paper"]["success"]) for r in sel)
            lines.append(f"| **mean** | {mode} | {n}/{len(sel)} | {_f(_mean(sel, 'refined', 'paper', 'E_t'))} | "
                         f"{_f(_mean(sel, 'refined', 'paper', 'E_r'))} | {_f(_mean(sel, 'refined', 'paper', 'E_a'))} | "
                         f"{_f(_mean(sel, 'refined', 'paper', 'E_j'))} | "
                         f"{_f(_mean(sel, 'refined', 'paper', 'penetration_max_mm'))} | "
                         f"{_f(statistics.median(r['wall_s'] for r in sel), 0)} |")
    return lines


def render(rows: list[dict[str, Any]], by_mode: dict[str, list[dict[str, Any]]], args: argparse.Namespace) -> str:
    digests = getattr(args, "digests", None)
    made = f" (rows made by common/ + worker/ digests {digests})" if digests else ""
    out = [
        "# Two hands and articulated objects on ARCTIC (issue #52)",
        "",
        f"Written {datetime.now(UTC):%Y-%m-%d %H:%M} UTC by `bench/arctic.py` ({args.two_hands}); "
        f"{args.provenance}{made}. Sequences: every dexmachina-processed ARCTIC sequence whose object folder has "
        f"its URDF ({len(rows)}). Goals (paper's protocol): most succeed, E_t <= {GOALS['E_t']} cm, E_r <= "
        f"{GOALS['E_r']} deg, E_a <= {GOALS['E_a']} deg, penetration max <= {GOALS['pen_max']} mm, <= 15 min per "
        "sequence on 2 threads.",
        "",
        "## Paper's protocol (frames 10 onward)",
        "",
        *table(rows, "paper"),
        "",
        "## All frames",
        "",
        *table(rows, "all"),
        "",
        "## Where the refined sequences fail",
        "",
        *failures(rows, args),
    ]
    if len(by_mode) > 1:
        out += ["", "## One CMA-ES per hand vs one over both hands (refined, paper's protocol)", "",
                *comparison(by_mode)]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    wanted = KERNELS[args.kernels]
    if any(os.environ.get(k) != v for k, v in wanted.items()):  # NumPy reads them once, when it is imported
        argv = sys.argv[1:] if argv is None else argv
        os.execve(sys.executable, [sys.executable, str(Path(__file__).resolve()), *argv], {**os.environ, **wanted})
    forced = "" if args.kernels == "original" else f" (kernels forced: {args.kernels}, {wanted})"
    forced += f" (CMA-ES settings other than the product's: {args.cma_overrides})" if args.cma_overrides else ""
    if args.kernels != "original":
        print(f"NumPy / OpenBLAS kernels: {args.kernels}; NumPy dispatches to: {numpy_simd()}", file=sys.stderr)
    digest = code_digest()
    args.provenance = provenance_line(digest) + forced
    cache_root = ROOT / "var" / "bench" / "arctic"
    paths = usable_sequences(args.arctic)
    if args.only:
        paths = [p for p in paths if p.stem in args.only or f"{p.parent.name}/{p.stem}" in args.only]
    if not paths:
        print(f"no usable ARCTIC sequence under {args.arctic}", file=sys.stderr)
        return 2
    by_mode: dict[str, list[dict[str, Any]]] = {}
    if args.compare:  # each mode's newest cached run, whatever code made it (the header names it)
        for mode in ("per_hand", "joint"):
            runs = sorted((cache_root / mode).glob("*/"), key=lambda d: d.stat().st_mtime)
            if not runs:
                continue
            cache = runs[-1]
            rows = [json.loads((cache / f"{p.parent.name}_{p.stem}.json").read_text()) for p in paths
                    if (cache / f"{p.parent.name}_{p.stem}.json").is_file()]
            if rows:
                by_mode[mode] = rows
                args.digests = {**getattr(args, "digests", {}), mode: cache.name}
        rows = by_mode.get(args.two_hands, [])
    else:
        rows = []
        for i, path in enumerate(paths, 1):
            print(f"[{i}/{len(paths)}] {path.parent.name}/{path.stem}", flush=True)
            rows.append(run_one(path, args, cache_root / args.two_hands / f"{digest}{plan_key(args)}"))
            r = rows[-1]["refined"]["paper"]
            print(f"  success {r['success']}  E_t {_f(r['E_t'])}  E_r {_f(r['E_r'])}  E_a {_f(r['E_a'])}  "
                  f"wall {rows[-1]['wall_s']:.0f} s", flush=True)
        by_mode[args.two_hands] = rows
    args.out.write_text(render(rows, by_mode, args))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
