"""Speed at the same fidelity: physics and CMA-ES variants side by side on one sample (issue #19, "must show").

    .venv/bin/python bench/speed.py --sample dev40 --variants before-19,default
    .venv/bin/python bench/speed.py --sample dev40 --limit 10 --variants default,noslip0-imp1,noslip0-imp30 \\
        --out bench/results/speed_experiments.md
    .venv/bin/python bench/speed.py --list            # the variants and what each changes

Each variant is a set of ``SimConfig`` / ``CmaSettings`` overrides (``VARIANTS``); ``default`` is the product as
it is. Every sequence of the sample is refined once per variant, the variants interleaved sequence by sequence
so that a change in the machine's load falls on all of them alike, with ``bench/refine.py``'s ``run_one`` (same
per-sequence cache in ``var/bench/refine/``, keyed by the overrides and a hash of the sources). One row per
variant: median and p90 wall seconds per sequence, physics steps per second inside simulation, physics steps
per sequence, success (final and first attempt), E_t / E_r / E_j / E_ft on the paper's protocol (frames 10
onward), penetration; then each variant's change against the first one. Writes ``bench/results/speed.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.refine import aggregate, run_one, sim_defaults  # noqa: E402

#: The configuration of main before issue #19 (noslip pass, MuJoCo's impratio, every CMA-ES generation run).
BEFORE_19_SIM: dict[str, Any] = {"noslip_iterations": 10, "impratio": 1.0, "contact_solimp": (0.9, 0.99, 0.001),
                                 "jacobian": "auto", "table_fit_s": 0.5, "table_shelf": False,
                                 "hold_until_m": 0.0}
BEFORE_19_CMA: dict[str, Any] = {"stall_generations": 0}
#: Loss terms added since (issue #15's grasp_reach), off as they were then.
BEFORE_19_WEIGHTS: dict[str, float] = {"grasp_reach": 0.0}


@dataclass(frozen=True)
class Variant:
    """One configuration of a speed run: what it changes against the product's defaults, and why."""

    sim: dict[str, Any]  # ``SimConfig`` overrides
    cma: dict[str, Any]  # ``CmaSettings`` overrides
    what: str
    weights: dict[str, float] = field(default_factory=dict)  # ``JobOptions.loss_weights`` overrides
    threads: int | None = None  # simulation threads per sequence (None: the run's ``--threads``)


def _on_before_19(sim: dict[str, Any], cma: dict[str, Any], what: str) -> Variant:
    """An experiment as it was measured: main before issue #19 with these settings changed, so it means the same
    whatever the product's defaults become."""
    return Variant({**BEFORE_19_SIM, **sim}, {**BEFORE_19_CMA, **cma}, what, dict(BEFORE_19_WEIGHTS))


NOSLIP0_IMP10: dict[str, Any] = {"noslip_iterations": 0, "impratio": 10.0}
SOLIMP99: dict[str, Any] = {"contact_solimp": (0.99, 0.995, 0.001)}
#: The gated early stop: 3 generations, below 15 (1 per frame at DexYCB's 5-frame keyframe interval; the
#: escalation level is 2.5 per frame).
STALL3LOW: dict[str, Any] = {"stall_generations": 3, "stall_below": 15.0}

VARIANTS: dict[str, Variant] = {
    "default": Variant({}, {}, "the product's defaults as they are"),
    "default-1-thread": Variant({}, {}, "the product's defaults on 1 simulation thread (issue #19 item 3: one "
                                "sequence on 2 threads in <= 0.6x its 1-thread time)", threads=1),
    "dense": Variant({"jacobian": "auto"}, {}, "the defaults with MuJoCo's automatic Jacobian (dense for one "
                     "hand), as before the sparse one became the default"),
    "solimp-0.9": Variant({"contact_solimp": (0.9, 0.99, 0.001)}, {}, "the defaults with the softer contact "
                          "impedance of main before issue #19 (0.9-0.99): the alternative that kept E_r within the "
                          "keep rule"),
    "solimp-0.995": Variant({"contact_solimp": (0.995, 0.998, 0.001)}, {}, "the defaults with a stiffer contact "
                            "impedance (0.995-0.998): steady penetration under a load scales with (1 - d) / d, 0.5x"),
    "solimp-0.998": Variant({"contact_solimp": (0.998, 0.999, 0.001)}, {}, "the defaults with a stiffer contact "
                            "impedance still (0.998-0.999): (1 - d) / d 0.2x the default's"),
    "dt-360": Variant({"timestep": 1.0 / 360.0}, {}, "the defaults with a 1/360 s timestep: the contact time "
                      "constant's floor (two timesteps) 5.6 instead of 8.3 ms, steady penetration in theory x0.44, "
                      "x1.5 the steps"),
    "dt-480": Variant({"timestep": 1.0 / 480.0}, {}, "the defaults with a 1/480 s timestep: time constant floor "
                      "4.2 ms, steady penetration in theory x0.25, x2 the steps"),
    "pen-0": Variant({}, {}, "the defaults without the penetration loss term (as before screen 11)",
                     weights={"penetration": 0.0}),
    "pen-0.3": Variant({}, {}, "the defaults with the penetration loss term ((depth / 1 mm)^2 per frame) at "
                       "weight 0.3", weights={"penetration": 0.3}),
    "pen-1": Variant({}, {}, "the defaults with the penetration loss term at weight 1",
                     weights={"penetration": 1.0}),
    "before-19": _on_before_19({}, {}, "main before issue #19: 10 noslip iterations, impratio 1, solimp 0.9-0.99"),
    "noslip0-imp1": _on_before_19({"noslip_iterations": 0}, {}, "no noslip pass, MuJoCo's impratio 1"),
    "noslip0-imp10": _on_before_19(NOSLIP0_IMP10, {}, "no noslip pass, impratio 10"),
    "noslip0-imp30": _on_before_19({"noslip_iterations": 0, "impratio": 30.0}, {}, "no noslip pass, impratio 30"),
    "noslip0-imp100": _on_before_19({"noslip_iterations": 0, "impratio": 100.0}, {}, "no noslip pass, impratio 100"),
    "noslip0-imp10-condim4": _on_before_19(
        {**NOSLIP0_IMP10, "hand_condim": 4, "object_condim": 4}, {},
        "no noslip, impratio 10, condim 4 on hand and object (no rolling friction: 2 constraint rows less)",
    ),
    "noslip0-imp10-solimp99": _on_before_19(
        {**NOSLIP0_IMP10, **SOLIMP99}, {},
        "no noslip, impratio 10, contact impedance 0.99-0.995 (stiffer from the first 0.1 mm: less penetration)",
    ),
    "noslip0-imp10-stall3": _on_before_19(
        NOSLIP0_IMP10, {"stall_generations": 3},
        "no noslip, impratio 10, a window's CMA-ES stops when its best loss improved < 1 % in 3 generations",
    ),
    "noslip0-imp10-stall3low": _on_before_19(
        NOSLIP0_IMP10, STALL3LOW,
        "no noslip, impratio 10, early stop as above but only for windows whose best loss is already below 15 "
        "(1 per frame at DexYCB's 5-frame keyframe interval; the escalation level is 2.5)",
    ),
    "noslip0-imp10-solimp99-stall3low": _on_before_19(
        {**NOSLIP0_IMP10, **SOLIMP99}, STALL3LOW,
        "the stiffer contact impedance and the gated early stop together (the default since issue #19)",
    ),
}



def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sample", default="dev40", help="sample list name in bench/samples (default dev40)")
    p.add_argument("--limit", type=int, default=None, help="only the first N sequences of the sample")
    p.add_argument("--variants", default="before-19,default",
                   help="comma-separated names from --list; the first is the reference (default before-19,default)")
    p.add_argument("--threads", type=int, default=2, help="simulation threads per sequence (default 2)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fresh", action="store_true", help="ignore cached per-sequence results")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "speed.md")
    p.add_argument("--list", action="store_true", help="print the variants and exit")
    args = p.parse_args(argv)
    args.variant_names = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in args.variant_names if v not in VARIANTS]
    if unknown:
        p.error(f"unknown variants {', '.join(unknown)}; known: {', '.join(VARIANTS)}")
    return args


def run_args(args: argparse.Namespace, variant: str) -> argparse.Namespace:
    """The ``bench/refine.py`` arguments ``run_one`` reads, for one variant."""
    v = VARIANTS[variant]
    return argparse.Namespace(popsize=None, max_generations=None, seed=args.seed,
                              threads=args.threads if v.threads is None else v.threads,
                              fresh=args.fresh, sim_overrides=v.sim, cma_overrides=v.cma, loss_weights=v.weights)


def p90(values: list[float]) -> float:
    return statistics.quantiles(values, n=10, method="inclusive")[-1] if len(values) > 1 else values[0]


def figures(rows: list[dict[str, Any]]) -> dict[str, float]:
    """One variant's row: speed and fidelity (paper protocol) over its sequences."""
    walls = [r["bench_wall_s"] for r in rows]
    steps = [r["timings"]["steps"] for r in rows]
    sim_s = sum(r["timings"]["sim_s"] for r in rows)
    paper = aggregate(rows, "refined", "paper")
    return {
        "n": len(rows),
        "median_s": statistics.median(walls),
        "p90_s": p90(walls),
        "total_s": sum(walls),
        "steps_per_s": sum(steps) / max(sim_s, 1e-9),
        "steps_per_seq": statistics.fmean(steps),
        **{k: paper[k] for k in ("SR", "SR_first", "E_t", "E_r", "E_j", "E_ft", "pen_mean", "pen_max_mean",
                                 "pen_max_max")},
    }


def thread_scaling(args: argparse.Namespace, rows: dict[str, list[dict[str, Any]]]) -> list[str]:
    """For each variant run on its own thread count beside the same configuration on the run's ``--threads``:
    the time of one sequence on ``--threads`` threads as a share of its time on the variant's (issue #19 item 3),
    over the summed times, the median sequence and the median of the per-sequence ratios."""
    lines = []
    for name in args.variant_names:
        v = VARIANTS[name]
        twins = [o for o in args.variant_names if o != name and VARIANTS[o].threads is None
                 and (VARIANTS[o].sim, VARIANTS[o].cma, VARIANTS[o].weights) == (v.sim, v.cma, v.weights)]
        if v.threads is None or not twins:
            continue
        many, few = [r["bench_wall_s"] for r in rows[twins[0]]], [r["bench_wall_s"] for r in rows[name]]
        lines.append(
            f"* `{twins[0]}` ({args.threads} threads) against `{name}` ({v.threads}): total time x"
            f"{sum(many) / sum(few):.2f}, median x{statistics.median(many) / statistics.median(few):.2f}, "
            f"per-sequence ratio median x{statistics.median(a / b for a, b in zip(many, few, strict=True)):.2f}"
        )
    return ["", "Thread scaling (the same configuration, one sequence at a time):", "", *lines] if lines else []


def render(args: argparse.Namespace, results: dict[str, dict[str, float]], names: list[str], started: str,
           load: tuple[tuple[float, ...], tuple[float, ...]], scaling: list[str] | None = None) -> str:
    ref_name = args.variant_names[0]
    ref = results[ref_name]
    lines = [
        "# Speed at the same fidelity (bench/speed.py, issue #19)",
        "",
        f"Generated on {started} UTC: sample `{args.sample}`, {len(names)} sequences"
        f"{f' (the first {args.limit})' if args.limit else ''}, {args.threads} simulation threads per sequence "
        "(unless a variant says otherwise), "
        f"seed {args.seed}, variants interleaved sequence by sequence. Machine: {os.cpu_count()} cores "
        f"({platform.processor() or platform.machine()}), load average before {load[0][0]:.2f} / after "
        f"{load[1][0]:.2f} (1 min), {load[1][2]:.2f} over the last 15 min at the end. Fidelity on the paper's "
        "protocol (frames 10 onward); penetration is the per-frame deepest hand-object contact.",
        "",
        "| variant | what | median s / seq | p90 s / seq | physics steps / s | steps / seq | SR % | SR 1st % | "
        "E_t cm | E_r deg | E_j cm | E_ft cm | penetration mm (mean per-frame max) | seq max mm (mean / worst) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in args.variant_names:
        f = results[name]
        lines.append(
            f"| `{name}` | {VARIANTS[name].what} | {f['median_s']:.1f} | {f['p90_s']:.1f} | {f['steps_per_s']:.0f} | "
            f"{f['steps_per_seq']:.0f} | {f['SR']:.1f} | {f['SR_first']:.1f} | {f['E_t']:.2f} | {f['E_r']:.2f} | "
            f"{f['E_j']:.2f} | {f['E_ft']:.2f} | {f['pen_mean']:.2f} | {f['pen_max_mean']:.2f} / "
            f"{f['pen_max_max']:.2f} |"
        )
    lines += ["", f"Against `{ref_name}` (keep rule of issue #19: SR not lower, E_t / E_r not more than 0.05 cm / "
              "0.2 deg worse, penetration not worse):", ""]
    for name in args.variant_names[1:]:
        f = results[name]
        keep = (f["SR"] >= ref["SR"] and f["E_t"] <= ref["E_t"] + 0.05 and f["E_r"] <= ref["E_r"] + 0.2
                and f["pen_mean"] <= ref["pen_mean"] + 0.05)
        lines.append(
            f"* `{name}`: median x{f['median_s'] / ref['median_s']:.2f}, total time x"
            f"{f['total_s'] / ref['total_s']:.2f}, physics rate x{f['steps_per_s'] / ref['steps_per_s']:.2f}, steps "
            f"x{f['steps_per_seq'] / ref['steps_per_seq']:.2f}; SR {f['SR'] - ref['SR']:+.1f} points, E_t "
            f"{f['E_t'] - ref['E_t']:+.2f} cm, E_r {f['E_r'] - ref['E_r']:+.2f} deg, penetration "
            f"{f['pen_mean'] - ref['pen_mean']:+.2f} mm: fidelity {'within' if keep else 'OUTSIDE'} the keep rule"
        )
    lines += scaling or []
    from worker.refine.run import STALL_GENERATIONS, STALL_LOSS_PER_FRAME

    touched = sorted({k for v in VARIANTS.values() for k in v.sim})
    defaults = sim_defaults()
    lines += ["", "The product's defaults when this ran (what `default` means here): "
              + ", ".join(f"`{k}={defaults[k]}`" for k in touched)
              + f", early stop after `{STALL_GENERATIONS}` stalled generations below `{STALL_LOSS_PER_FRAME}` "
              "loss per frame.", ""]
    lines += ["Variants (``SimConfig`` / ``CmaSettings`` overrides):", ""]
    for name in args.variant_names:
        v = VARIANTS[name]
        lines.append(f"* `{name}`: sim {v.sim or '{}'}, CMA-ES {v.cma or '{}'}"
                     + (f", loss weights {v.weights}" if v.weights else "")
                     + (f", {v.threads} simulation thread(s)" if v.threads is not None else ""))
    lines += ["", "Sequences:", "", *(f"- `{n}`" for n in names)]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from bench.samples.draw import read_sample
    from common.dexycb import shared_data_dir

    args = parse_args(argv)
    if args.list:
        for name, v in VARIANTS.items():
            print(f"{name:24s} {v.what}\n{'':24s} sim {v.sim or '{}'} cma {v.cma or '{}'} weights {v.weights or '{}'}"
                  + (f" threads {v.threads}" if v.threads is not None else ""))
        return 0
    data = shared_data_dir()
    if data is None:
        print("bench/speed.py: ../shared/data is not present", file=sys.stderr)
        return 2
    sample = read_sample(ROOT / "bench" / "samples" / f"{args.sample}.txt")
    todo = sample[: args.limit] if args.limit else sample
    started = datetime.now(UTC).strftime("%Y-%m-%d %H:%M")
    load_before = os.getloadavg()
    cache = ROOT / "var" / "bench" / "refine"
    rows: dict[str, list[dict[str, Any]]] = {v: [] for v in args.variant_names}
    t0 = time.perf_counter()
    for i, (name, awkward) in enumerate(todo, 1):
        for variant in args.variant_names:
            row = run_one(data / "dexycb" / "dev" / name, run_args(args, variant), cache, awkward)
            rows[variant].append(row)
            b = row["metrics"]["refined"]
            print(f"[{i}/{len(todo)}] {variant:22s} {name}: {'ok' if b['success'] else 'FAIL'} "
                  f"E_t {b['E_t']:.2f} E_r {b['E_r']:.2f} {row['bench_wall_s']:.1f}s "
                  f"({row['timings']['steps_per_second']:.0f} steps/s)  [{time.perf_counter() - t0:.0f}s]", flush=True)
    results = {v: figures(r) for v, r in rows.items()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(render(args, results, [n for n, _ in todo], started, (load_before, os.getloadavg()),
                                    thread_scaling(args, rows)))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
