"""Jumps in the recorded object pose against refinement failures (issue #15: what caps the success rate).

    .venv/bin/python bench/reference_jumps.py --sample dev120 --report bench/results/refine_dev120.md

A DexYCB object pose is fitted per video frame, and now and then it turns by tens of degrees from one frame to
the next (at 30 fps, 45 deg a frame is 1,350 deg/s; a hand lifting an object turns it by a few degrees a frame).
No simulated object follows such a step, and the success criterion (every frame within 3 cm and 30 deg) counts
the frames after it. This reads each sequence of the sample, finds its largest frame-to-frame rotation of the
recorded object (and about which of the object's principal axes it turns: a spin about a symmetry axis is a
pose the images cannot tell apart), takes success / failure from a ``bench/refine.py`` report of the same
sample, and writes how often each outcome has such a jump, and the success rate over the sequences without one.
Nothing is refined; it runs in seconds. Writes ``bench/results/reference_jumps.md`` (``--out``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Container
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from common.geometry import FloatArray, quat_axis_angle, quat_conj, quat_mul  # noqa: E402
from common.sequence import Sequence  # noqa: E402

#: Frame-to-frame rotations (deg) the report counts; the last but one is the one it splits the sample by.
THRESHOLDS_DEG = (20.0, 30.0, 45.0, 60.0)
SPLIT_DEG = 45.0
AXES = ("short", "middle", "long")


@dataclass(frozen=True)
class PoseJump:
    """The largest frame-to-frame change of a recorded object pose track."""

    rotation_deg: float  # the largest rotation between consecutive frames
    frame: int  # it happens between this frame and the next
    axis: str  # the object's principal axis (by extent) it turns about most: short, middle or long
    axis_cos: float  # |cos| between the rotation axis and that principal axis
    translation_cm: float  # the largest translation between consecutive frames (anywhere)


def frame_rotation_steps(quat: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(T-1,) rotation angle in degrees between consecutive (w, x, y, z) quaternions, and (T-1, 3) its unit axis
    in the object's own frame (q_t^-1 q_t+1: the step as the object sees it)."""
    axis, angle = quat_axis_angle(quat_mul(quat_conj(quat[:-1]), quat[1:]))
    return np.degrees(angle), axis


def principal_axes(vertices: FloatArray) -> FloatArray:
    """(3, 3) columns: the object's principal directions, from its shortest extent to its longest."""
    centred = vertices - vertices.mean(axis=0)
    _, vecs = np.linalg.eigh(np.cov(centred.T))
    extents = np.ptp(centred @ vecs, axis=0)
    return vecs[:, np.argsort(extents)]


def largest_jump(pose: FloatArray, vertices: FloatArray) -> PoseJump:
    """The largest frame-to-frame step of a (T, 7) pose track (x y z qw qx qy qz) of an object with these
    surface vertices (object frame)."""
    angle, axis = frame_rotation_steps(pose[:, 3:])
    k = int(np.argmax(angle))
    cosines = np.abs(axis[k] @ principal_axes(vertices))
    a = int(np.argmax(cosines))
    translation = 100.0 * np.linalg.norm(np.diff(pose[:, :3], axis=0), axis=1)
    return PoseJump(float(angle[k]), k, AXES[a], float(cosines[a]), float(translation.max()))


def read_sequence_rows(report: Path) -> dict[str, dict[str, str]]:
    """Sequence stem -> {column: cell} from the per-sequence table of a ``bench/refine.py`` report."""
    lines = report.read_text().splitlines()
    header = next((i for i, line in enumerate(lines) if line.startswith("| sequence |")), None)
    if header is None:
        raise SystemExit(f"{report}: no per-sequence table (a bench/refine.py report has one)")
    columns = [c.strip() for c in lines[header].strip("|").split("|")]
    rows = {}
    for line in lines[header + 2:]:
        if not line.startswith("|"):
            break
        row = dict(zip(columns, (c.strip() for c in line.strip("|").split("|")), strict=False))
        rows[row["sequence"]] = row
    return rows


def refined_ok(row: dict[str, str]) -> bool:
    """The refined success of one per-sequence row (its column reads "yes (...)" or "no (...)")."""
    return next(v for k, v in row.items() if k.startswith("refined ok")).startswith("yes")


def read_outcomes(report: Path) -> dict[str, bool]:
    """Sequence stem -> refined success, from the per-sequence table of a ``bench/refine.py`` report."""
    return {stem: refined_ok(row) for stem, row in read_sequence_rows(report).items()}


def render(args: argparse.Namespace, rows: list[tuple[str, str, bool, PoseJump]]) -> str:
    fails = [r for r in rows if not r[2]]
    wins = [r for r in rows if r[2]]
    lines = [
        "# Jumps in the recorded object pose against refinement failures (bench/reference_jumps.py)",
        "",
        f"Generated on {datetime.now(UTC):%Y-%m-%d %H:%M} UTC: sample `{args.sample}` ({len(rows)} sequences), "
        f"outcomes from `{args.report.relative_to(ROOT) if args.report.is_relative_to(ROOT) else args.report}`. "
        "A jump is the largest rotation of the recorded object between two consecutive frames (30 fps).",
        "",
        "| largest step above | failures | successes |",
        "|---|---|---|",
    ]
    for t in THRESHOLDS_DEG:
        lines.append(f"| {t:.0f} deg / frame | {sum(r[3].rotation_deg > t for r in fails)} of {len(fails)} | "
                     f"{sum(r[3].rotation_deg > t for r in wins)} of {len(wins)} |")
    calm = [r for r in rows if r[3].rotation_deg <= SPLIT_DEG]
    sr_all = 100.0 * len(wins) / max(len(rows), 1)
    sr_calm = 100.0 * sum(r[2] for r in calm) / max(len(calm), 1)
    lines += ["", f"Success rate: {sr_all:.1f} % of all {len(rows)}; {sr_calm:.1f} % of the {len(calm)} whose "
              f"recording never turns more than {SPLIT_DEG:.0f} deg in a frame (the paper's protocol counts them "
              "all; this split is a diagnosis, not a figure to compare with it).", "",
              f"Sequences with a step above {THRESHOLDS_DEG[0]:.0f} deg / frame, and every failure (the axis: the "
              "object's principal direction, by extent, closest to the step's rotation axis; where two extents are "
              "equal, as the diameters of a can, which of the two it names is arbitrary):", "",
              "| sequence | object | refined | largest step deg | between frames | about the object's | |cos| | "
              "largest translation step cm |", "|---|---|---|---|---|---|---|---|"]
    for stem, obj, ok, j in sorted(rows, key=lambda r: -r[3].rotation_deg):
        if j.rotation_deg > THRESHOLDS_DEG[0] or not ok:
            lines.append(f"| {stem} | {obj} | {'ok' if ok else 'FAIL'} | {j.rotation_deg:.1f} | "
                         f"{j.frame}-{j.frame + 1} | {j.axis} axis | {j.axis_cos:.2f} | {j.translation_cm:.1f} |")
    return "\n".join(lines) + "\n"


def parse_report_args(argv: list[str] | None, description: str, default_out: str) -> argparse.Namespace:
    """``--sample``, ``--report`` (default: that sample's ``bench/refine.py`` report) and ``--out``, shared by the
    scripts that read a sample's recordings beside its refine report."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--sample", default="dev120", help="sample list in bench/samples (default dev120)")
    p.add_argument("--report", type=Path, default=None,
                   help="bench/refine.py report of that sample (default bench/results/refine_<sample>.md)")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / default_out)
    args = p.parse_args(argv)
    if args.report is None:
        args.report = ROOT / "bench" / "results" / ("refine_dev.md" if args.sample == "dev40"
                                                    else f"refine_{args.sample}.md")
    return args


def load_sample(args: argparse.Namespace, reported: Container[str], script: str) -> list[tuple[str, Sequence]] | None:
    """(stem, sequence) for each recording of ``args.sample``, each of which the report must have a row for
    (``reported``); None, with a message, when ../shared/data is not present."""
    from bench.samples.draw import read_sample
    from common.dexycb import load_dexycb_npz, shared_data_dir

    data = shared_data_dir()
    if data is None:
        print(f"{script}: ../shared/data is not present", file=sys.stderr)
        return None
    out = []
    for name, _ in read_sample(ROOT / "bench" / "samples" / f"{args.sample}.txt"):
        stem = name.removesuffix(".npz")
        if stem not in reported:
            raise SystemExit(f"{args.report} has no row for {stem}: run bench/refine.py --sample {args.sample}")
        out.append((stem, load_dexycb_npz(data / "dexycb" / "dev" / name)))
    return out


def write_report(args: argparse.Namespace, text: str) -> None:
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


def main(argv: list[str] | None = None) -> int:
    args = parse_report_args(argv, __doc__.split("\n\n")[0], "reference_jumps.md")
    outcomes = read_outcomes(args.report)
    sample = load_sample(args, outcomes, "bench/reference_jumps.py")
    if sample is None:
        return 2
    rows = [(stem, seq.object.name, outcomes[stem], largest_jump(seq.object_pose, seq.object.surface_vertices()))
            for stem, seq in sample]
    write_report(args, render(args, rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
