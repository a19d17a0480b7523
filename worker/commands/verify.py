"""``hoi-refine verify RESULT.npz``: recompute everything a result claims from its embedded sequence and stored
controls (``worker.verification.check``), fail naming each field that differs, flag a non-default physics config, and
print the largest deviation and the digests. ``hoi-refine verify DIR``: every result under a folder or a dataset
release, in parallel (``worker.commands.verify_folder``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from common.settings import get_settings


def register(subparsers: Any) -> None:
    v = subparsers.add_parser(
        "verify",
        help="recompute everything a result claims from its embedded sequence and stored controls",
        description="Re-runs the raw and the refined replay (and every restart) from the embedded sequence and "
        "the stored keyframes in a fresh model, recomputes every derived array and figure (object trajectory, "
        "simulated keypoints, wrist track, contacts, per-frame and summary metrics on both protocols, success) "
        "and fails naming each field that differs and by how much. A physics config other than the product's "
        "defaults fails unless --allow-config. A result that stores every frame's integration state is checked "
        "stepwise: each frame from the stored one before it, under the stored inputs of every physics step once "
        "they match the keyframes' (micrometres on any host), every array and figure "
        "against what those states give, the whole re-simulation's drift reported; an older result is compared "
        "with the whole re-simulation, bit-identical on the machine that made it and within physical tolerances "
        "(millimetres for a held object) on another x86_64 host. "
        "Prints the largest trajectory deviation, a SHA-256 over everything checked, and the result's content "
        "sha256 (every member but the wall-clock timings), which two runs with the same input, options and seed "
        "share. Given a folder (or a dataset release from `hoi-refine dataset export`), checks every *.result.npz "
        "under it on --jobs processes, with a progress bar, a summary table (passed / failed / unreadable, and "
        "per failing file its first failing field and frame) and, with --report, a JSON report; a release's "
        "SHA256SUMS is checked too. A file that fails or cannot be read does not stop the others. Exit code: 0 "
        "all passed, 1 some failed or could not be read, 2 bad input (no such path, no results in the folder).",
    )
    v.add_argument("result", type=Path, metavar="RESULT_OR_DIR",
                   help="result file written by `hoi-refine refine`, or a folder of them / a dataset release")
    v.add_argument("--sequence", type=Path, default=None, help="sequence file (default: the one embedded)")
    v.add_argument("--allow-config", action="store_true",
                   help="accept a physics config that differs from the defaults (the differences are printed)")
    v.add_argument("--threads", type=int, default=1,
                   help="replays run side by side on this many threads (default 1; the figures do not depend on it)")
    v.add_argument("--jobs", type=int, default=None,
                   help="a folder: files checked side by side on this many processes (default: one per 2 MB of "
                        "result files, up to the core count; a handful of small results are checked in this "
                        "process, since starting a checker process costs seconds)")
    v.add_argument("--report", type=Path, default=None,
                   help="a folder: write the JSON report (every file's status, failures, figures) here")
    v.set_defaults(func=_verify)


def _verify(args: argparse.Namespace) -> int:
    from common.errors import ConfigurationError

    if args.result.is_dir():
        from worker.commands.verify_folder import verify_folder

        if args.sequence is not None or args.threads != 1:
            raise ConfigurationError("--sequence and --threads apply to one result file (a folder: --jobs)")
        return verify_folder(args.result, jobs=args.jobs, report_path=args.report, allow_config=args.allow_config)
    if args.jobs is not None or args.report is not None:
        raise ConfigurationError("--jobs and --report apply to a folder of results")
    from common.errors import ResultMismatchError
    from common.result_format import content_digest
    from common.sequence_io import load_sequence
    from worker.verification import check_result

    seq = load_sequence(args.sequence) if args.sequence else None
    blob = args.result.read_bytes()
    settings = get_settings()
    report = check_result(blob, seq, allow_config=args.allow_config, cache_dir=settings.resolved_cache_dir(),
                          mano_dir=settings.mano_dir, threads=max(1, args.threads))
    if report.config_changes:
        banner = "!" * 78
        print(banner)
        print("NON-DEFAULT PHYSICS CONFIG" + (" (accepted by --allow-config)" if args.allow_config else ""))
        for name, default, stored in report.config_changes:
            print(f"  {name}: {stored!r} (default {default!r})")
        print(banner)
    for note in report.config_notes:
        print(f"note: {note}")
    how = "bit-identical" if report.exact else (
        "stepwise" if report.method == "stepwise" else "within the cross-host tolerances")
    for rep in report.stepwise.values():
        name, dev = rep.worst()
        exact = "bit-identical" if rep.exact else f"largest {name} deviation {dev.value:.3g} at frame {dev.frame} " \
            f"({dev.where})"
        inputs = "under the inputs made here" if rep.controls is None else \
            f"under the stored inputs (largest {rep.controls.value:.3g} from the keyframes')"
        print(f"stepwise {rep.key}: {rep.frames} frames each from the stored one before {inputs}, {exact}, "
              f"{rep.seconds:.2f} s")
    whole = "whole-rollout drift" if report.method == "stepwise" else "largest object deviation"
    print(f"re-simulated {report.frames} frames: {whole} {report.max_pos_diff_m * 1000:.4g} mm / "
          f"{report.max_rot_diff_deg:.4g} deg, keypoints {report.max_keypoint_diff_m * 1000:.4g} mm")
    print(f"checked sha256 {report.digest} ({len(report.checked)} fields)")
    # Equal for two runs with the same input, options and seed even when their wall-clock timings differ.
    print(f"content sha256 {content_digest(blob)} (all but the wall-clock timings)")
    if report.failures:
        raise ResultMismatchError("result does not verify:\n  " + "\n  ".join(report.failures))
    print(f"verify: OK - every checked field reproduced ({how})")
    return 0
