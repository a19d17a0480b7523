"""``hoi-refine refine`` and ``hoi-refine verify`` (issue #3 item 6), plus ``run_demo()`` for ``make demo``.

Heavy imports (MuJoCo, cma) stay inside the handlers so ``hoi-refine --help`` stays fast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from common.job_options import JobOptions
from common.job_options_cli import add_job_option_arguments, job_options_from_args


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "refine",
        help="optimise the hand motion of a sequence until the simulated object follows the recorded one",
        description="Windowed CMA-ES over spline keyframes (DESIGN §1.3-1.7); writes one result NPZ.",
    )
    p.add_argument("sequence", type=Path, help="sequence file (.npz native or DexYCB, .json, DexYCB folder)")
    p.add_argument("--out", type=Path, required=True, help="result file to write (.npz)")
    p.add_argument("--threads", type=int, default=1, help="simulation threads (default 1)")
    add_job_option_arguments(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--no-wall-clock",
        action="store_true",
        help="leave the wall-clock timings (seconds, rates, thread count) out of the result file, for "
        "reproducibility checks: two runs with the same input, options and seed then give identical files "
        "(the step and evaluation counters stay)",
    )
    p.set_defaults(func=_refine)

    v = subparsers.add_parser(
        "verify",
        help="re-simulate a result's stored controls and fail if the object trajectory differs",
        description="Re-simulates the stored keyframes from frame 0 and compares the object trajectory; also "
        "prints the result's content sha256 (every member but the wall-clock timings), which two runs with the "
        "same input, options and seed share.",
    )
    v.add_argument("result", type=Path, help="result file written by `hoi-refine refine`")
    v.add_argument("--sequence", type=Path, default=None, help="sequence file (default: the one embedded)")
    v.set_defaults(func=_verify)


def _load(path: Path) -> Any:
    """Any sequence file ``load_sequence`` reads (native NPZ/JSON, DexYCB NPZ or folder); missing -> clear error."""
    from common.sequence_io import load_sequence

    return load_sequence(path)


def _refine(args: argparse.Namespace) -> int:
    from worker.refine.run import refine_sequence

    options = job_options_from_args(args)  # before loading: a bad flag should not wait for a slow load
    seq = _load(args.sequence)
    outcome = refine_sequence(seq, options, threads=args.threads, progress=None if args.quiet else _ProgressBar())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_bytes(outcome.to_npz_bytes(wall_clock=not args.no_wall_clock))
    if not args.quiet:
        print(file=sys.stderr)
    print(format_metrics_table(outcome.summary))
    print(f"wrote {args.out}")
    return 0


def _verify(args: argparse.Namespace) -> int:
    from common.result_format import content_digest
    from worker.refine.result import verify_result

    seq = _load(args.sequence) if args.sequence else None
    blob = args.result.read_bytes()
    report = verify_result(blob, seq)
    print(f"verify: OK - object trajectory reproduced over {report['frames']} frames "
          f"(max position difference {report['max_pos_diff_m']:.3g} m)")
    # Equal for two runs with the same input, options and seed even when their wall-clock timings differ.
    print(f"content sha256 {content_digest(blob)} (all but the wall-clock timings)")
    return 0


class _ProgressBar:
    """Window i/N, best loss, evaluations, ETA: one rewritten line on a terminal; in a log (not a TTY), one
    line per finished window instead of hundreds of carriage-return updates."""

    def __init__(self) -> None:
        self._tty = sys.stderr.isatty()
        self._last_window = (0, -1)

    def __call__(self, p: Any) -> None:
        width = 24
        done = int(width * p.window / max(p.windows, 1))
        bar = "#" * done + "-" * (width - done)
        again = f"attempt {p.attempt} " if p.attempt > 1 else ""
        text = (
            f"[{bar}] {again}window {p.window}/{p.windows}  best loss {p.best_loss:9.3f}  "
            f"evals {p.evaluations:6d}  skipped {p.skipped}  elapsed {p.elapsed_s:5.1f}s  ETA {p.eta_s:5.1f}s"
        )
        if self._tty:
            sys.stderr.write(f"\r{text} ")
        elif (p.attempt, p.window) != self._last_window:
            sys.stderr.write(f"{text}\n")
            self._last_window = (p.attempt, p.window)
        sys.stderr.flush()


def format_metrics_table(summary: dict[str, Any]) -> str:
    """Raw replay vs refined: SR, E_t (cm), E_r (deg), E_j (cm), E_ft (cm)."""
    rows = [("", "success", "E_t cm", "E_r deg", "E_j cm", "E_ft cm")]
    for name in ("raw", "refined"):
        m = summary["metrics"][name]
        rows.append(
            (
                name,
                "yes" if m["success"] else "no",
                f"{m['E_t']:.2f}",
                f"{m['E_r']:.2f}",
                f"{m['E_j']:.2f}",
                f"{m['E_ft']:.2f}",
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    t = summary.get("timings", {})
    w = summary.get("windows", {})
    lines.append(
        f"wall {t.get('wall_s', 0):.1f}s, {t.get('sim_share', 0) * 100:.0f}% in simulation, "
        f"{t.get('steps', 0)} steps, {t.get('evaluations', 0)} candidate evaluations, "
        f"windows {w.get('count', 0)} ({w.get('skipped', 0)} skipped, {w.get('escalated', 0)} escalated)"
    )
    attempts = summary.get("attempts", [])
    if len(attempts) > 1:
        seeds = ", ".join(f"seed {a['seed']}: {'ok' if a['success'] else 'failed'}" for a in attempts)
        lines.append(f"{len(attempts)} attempts ({seeds}); the result is the best")
    return "\n".join(lines)


def run_demo(threads: int = 2, short: bool = False, out_dir: Path | str = Path("var/demo")) -> int:
    """Refine the built-in example in this process, print raw vs refined, and save the result, its video and
    its plots under ``out_dir`` (``hoi-refine demo --local``)."""
    from worker.example import example_sequence, short_example_sequence
    from worker.refine.run import refine_sequence
    from worker.visual import render_video, resimulate, write_plots

    seq = short_example_sequence() if short else example_sequence()
    outcome = refine_sequence(seq, JobOptions(), threads=threads, progress=_ProgressBar())
    print(file=sys.stderr)
    print(f"refined the built-in example {seq.name!r} ({seq.num_frames} frames)")
    print(format_metrics_table(outcome.summary))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    blob = outcome.to_npz_bytes()
    result, video = out / f"{seq.name}.result.npz", out / f"{seq.name}.mp4"
    result.write_bytes(blob)
    render_video(resimulate(blob), str(video))
    plots = write_plots(blob, out / f"{seq.name}_plots")
    print(f"result: {result}\nvideo: {video}\nplots: {', '.join(str(p) for p in plots)}")
    return 0
