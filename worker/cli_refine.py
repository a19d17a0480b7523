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
        help="recompute everything a result claims from its embedded sequence and stored controls",
        description="Re-runs the raw and the refined replay (and every restart) from the embedded sequence and "
        "the stored keyframes in a fresh model, recomputes every derived array and figure (object trajectory, "
        "simulated keypoints, wrist track, contacts, per-frame and summary metrics on both protocols, success) "
        "and fails naming each field that differs and by how much. A physics config other than the product's "
        "defaults fails unless --allow-config. On the machine that made the result the replay is bit-identical; "
        "on another x86_64 host it is compared within physical tolerances (worker/refine/verify.py). Prints the "
        "largest trajectory deviation, a SHA-256 over everything checked, and the result's content sha256 (every "
        "member but the wall-clock timings), which two runs with the same input, options and seed share.",
    )
    v.add_argument("result", type=Path, help="result file written by `hoi-refine refine`")
    v.add_argument("--sequence", type=Path, default=None, help="sequence file (default: the one embedded)")
    v.add_argument("--allow-config", action="store_true",
                   help="accept a physics config that differs from the defaults (the differences are printed)")
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
    from common.errors import ResultMismatchError
    from common.result_format import content_digest
    from worker.refine.verify import check_result

    seq = _load(args.sequence) if args.sequence else None
    blob = args.result.read_bytes()
    report = check_result(blob, seq, allow_config=args.allow_config)
    if report.config_changes:
        banner = "!" * 78
        print(banner)
        print("NON-DEFAULT PHYSICS CONFIG" + (" (accepted by --allow-config)" if args.allow_config else ""))
        for name, default, stored in report.config_changes:
            print(f"  {name}: {stored!r} (default {default!r})")
        print(banner)
    for note in report.config_notes:
        print(f"note: {note}")
    how = "bit-identical" if report.exact else "within the cross-host tolerances"
    print(f"re-simulated {report.frames} frames: largest object deviation {report.max_pos_diff_m * 1000:.4g} mm / "
          f"{report.max_rot_diff_deg:.4g} deg, keypoints {report.max_keypoint_diff_m * 1000:.4g} mm")
    print(f"checked sha256 {report.digest} ({len(report.checked)} fields)")
    # Equal for two runs with the same input, options and seed even when their wall-clock timings differ.
    print(f"content sha256 {content_digest(blob)} (all but the wall-clock timings)")
    if report.failures:
        raise ResultMismatchError("result does not verify:\n  " + "\n  ".join(report.failures))
    print(f"verify: OK - every checked field reproduced ({how})")
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
    """Raw replay vs refined on both protocols (all frames; the paper's, frames 10 onward): success (and the
    first attempt's), E_t (cm), E_r (deg), E_j (cm), E_ft (cm), penetration (mean per-frame maximum and sequence
    maximum, mm) and the share of lifted frames held by the hand alone."""
    rows = [("", "protocol", "success", "1st try", "E_t cm", "E_r deg", "E_j cm", "E_ft cm", "pen mm",
             "pen max", "hand-held")]
    for name in ("raw", "refined"):
        top = summary["metrics"][name]
        paper = top.get("paper")
        blocks = [("all frames", top)]
        if isinstance(paper, dict):
            blocks.append((f"frames {paper.get('first_frame', 10)}+", paper))
        for label, m in blocks:
            first = m.get("success_first_attempt")
            rows.append(
                (
                    name if label == "all frames" else "",
                    label,
                    _yes(m.get("success")),
                    "" if first is None else _yes(first),
                    _num(m.get("E_t")),
                    _num(m.get("E_r")),
                    _num(m.get("E_j")),
                    _num(m.get("E_ft")),
                    _num(m.get("penetration_mean_mm")),
                    _num(m.get("penetration_max_mm")),
                    _pct(m.get("hand_only_fraction")),
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
    lines.append("pen: deepest hand-object penetration per frame (mean, max); hand-held: lifted frames in which "
                 "only the hand touches the object")
    return "\n".join(lines)


def _yes(v: Any) -> str:
    return "-" if v is None else ("yes" if v else "no")


def _num(v: Any) -> str:
    return "-" if v is None or v != v else f"{float(v):.2f}"


def _pct(v: Any) -> str:
    return "-" if v is None else f"{100 * float(v):.0f}%"


def run_demo(threads: int = 2, short: bool = False) -> int:
    """Refine the built-in example and print raw vs refined (``make demo``)."""
    from worker.example import example_sequence, short_example_sequence
    from worker.refine.run import refine_sequence

    seq = short_example_sequence() if short else example_sequence()
    outcome = refine_sequence(seq, JobOptions(), threads=threads, progress=_ProgressBar())
    print(file=sys.stderr)
    print(f"refined the built-in example {seq.name!r} ({seq.num_frames} frames)")
    print(format_metrics_table(outcome.summary))
    return 0
