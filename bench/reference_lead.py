"""Recorded objects that move before the recorded hand reaches them (issue #15: what floors E_t and E_r).

    .venv/bin/python bench/reference_lead.py --sample dev120 --report bench/results/refine_dev120.md

In a simulation the object moves only through contact, and the refined hand stays near the recorded hand (the
wrist translation is the recording's; pose and wrist rotation are bounded offsets). In DexYCB the object pose
and the hand pose are fitted separately per video frame, and in many sequences the recorded object starts to
move while no recorded fingertip is near it: the annotations are out of step by a few frames, or the hand is
annotated centimetres off. Until the hand arrives, a simulated object stays where it rests, and every one of
those frames adds the recorded object's displacement from rest to the object error.

For each sequence of the sample this finds the frame the recorded object has moved from its start
(``worker.simulation.rest_pose.moved_frame``: 5 mm or 10 deg, the product's rule) and the first frame a recorded
fingertip of a valid hand frame is within ``CONTACT_THRESHOLD`` (1 cm, the product's fingertip-contact rule) of
the object's surface, and the *floor*: the recorded displacement from the start pose summed over the paper's
frames (10 onward) before that touch, divided by the number of those frames, i.e. what those frames alone add
to the sequence's mean E_t and E_r when the simulated object waits for the hand. A lower bound only for a hand
that follows its recording; a refinement may move the hand a little earlier. Reads the refined per-sequence
errors from a ``bench/refine.py`` report of the same sample for comparison. Nothing is refined; it runs in
seconds. Writes ``bench/results/reference_lead.md`` (``--out``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.reference_jumps import (  # noqa: E402
    load_sample,
    parse_report_args,
    read_sequence_rows,
    refined_ok,
    write_report,
)
from common.geometry import FloatArray, quat_conj, quat_rotate, rotation_error_deg  # noqa: E402
from common.primitive_surface import object_surface_points  # noqa: E402
from common.sequence import FINGERTIP_INDICES, Sequence  # noqa: E402

#: The paper's protocol leaves out the first frames of each sequence (``common.batch_metrics``' "frames 10+").
PAPER_FIRST_FRAME = 10
#: A fingertip this close to the surface (m) touches it (``worker.refine.losses.CONTACT_THRESHOLD``).
CONTACT_THRESHOLD = 0.01


@dataclass(frozen=True)
class Lead:
    """How far a recording's object runs ahead of its hand."""

    moved: int  # first frame the recorded object is 5 mm / 10 deg from its start pose (T if never)
    touch: int | None  # first valid frame a recorded fingertip is within CONTACT_THRESHOLD (None: never)
    floor_t_cm: float  # the untouched frames' contribution to the sequence's mean E_t (paper's frames)
    floor_r_deg: float  # ... to its mean E_r
    ahead_t_cm: float  # the part of floor_t_cm from frames the object has moved (``moved`` <= t < ``touch``)
    ahead_r_deg: float  # ... of floor_r_deg

    @property
    def lead_frames(self) -> int | None:
        """Frames the recorded object moves before the recorded hand touches it (<= 0: the hand is first)."""
        return None if self.touch is None else self.touch - self.moved


def first_touch(seq: Sequence, surface: FloatArray) -> int | None:
    """First frame at which a valid recorded fingertip of any hand is within CONTACT_THRESHOLD of the surface
    (object-frame points ``surface``), or None."""
    from scipy.spatial import cKDTree

    tree = cKDTree(surface)
    pose = seq.object_pose
    first: int | None = None
    for hand in seq.hands:
        if hand.keypoints is None:
            continue
        tips = hand.keypoints[:, list(FINGERTIP_INDICES)]  # (T, 5, 3), the object pose's (source) frame
        local = quat_rotate(quat_conj(pose[:, 3:])[:, None].repeat(tips.shape[1], 1), tips - pose[:, None, :3])
        dist, _ = tree.query(local.reshape(-1, 3))
        near = (np.asarray(dist).reshape(tips.shape[:2]) <= CONTACT_THRESHOLD).any(axis=1) & hand.valid
        hits = np.nonzero(near)[0]
        if hits.size and (first is None or hits[0] < first):
            first = int(hits[0])
    return first


def reference_lead(seq: Sequence) -> Lead:
    from worker.simulation.rest_pose import moved_frame

    pose = seq.object_pose
    t = pose.shape[0]
    touch = first_touch(seq, object_surface_points(seq.object))
    frames = np.arange(PAPER_FIRST_FRAME, t)
    untouched = frames[frames < (t if touch is None else touch)]
    shift = 100.0 * np.linalg.norm(pose[untouched, :3] - pose[0, :3], axis=1)
    turn = rotation_error_deg(pose[untouched, 3:], np.repeat(pose[:1, 3:], len(untouched), axis=0))
    moved = moved_frame(pose)
    ahead = untouched >= moved
    n = max(len(frames), 1)
    return Lead(moved, touch, float(shift.sum() / n), float(turn.sum() / n), float(shift[ahead].sum() / n),
                float(turn[ahead].sum() / n))


def read_errors(report: Path) -> dict[str, tuple[bool, float, float]]:
    """Sequence stem -> (refined success, E_t 10+ cm, E_r 10+ deg) from a ``bench/refine.py`` report."""
    return {stem: (refined_ok(row), float(row["E_t 10+"]), float(row["E_r 10+"]))
            for stem, row in read_sequence_rows(report).items()}


def render(args: argparse.Namespace, rows: list[tuple[str, str, Lead, tuple[bool, float, float]]]) -> str:
    n = len(rows)
    known = [r for r in rows if r[2].lead_frames is not None]
    ahead = [r for r in known if (r[2].lead_frames or 0) > 0]
    leads = [r[2].lead_frames or 0 for r in ahead]
    mean = statistics.fmean
    e_t, e_r = mean(r[3][1] for r in rows), mean(r[3][2] for r in rows)
    f_t, f_r = mean(r[2].floor_t_cm for r in rows), mean(r[2].floor_r_deg for r in rows)
    a_t, a_r = mean(r[2].ahead_t_cm for r in rows), mean(r[2].ahead_r_deg for r in rows)
    report = args.report.relative_to(ROOT) if args.report.is_relative_to(ROOT) else args.report
    lines = [
        "# Recorded objects that move before the recorded hand reaches them (bench/reference_lead.py)",
        "",
        f"Generated on {datetime.now(UTC):%Y-%m-%d %H:%M} UTC: sample `{args.sample}` ({n} sequences), refined "
        f"errors from `{report}` (paper's protocol, frames {PAPER_FIRST_FRAME}+). *Moved*: the first frame the "
        "recorded object is 5 mm or 10 deg from its start pose; *touch*: the first frame a recorded fingertip (valid "
        f"hand frames only) is within {100 * CONTACT_THRESHOLD:.0f} cm of its surface; *floor*: the recorded "
        "displacement from the start pose summed over the paper's frames before the touch, over the number of "
        "paper's frames, i.e. what those frames add to the sequence's mean error while the simulated object waits "
        "for the hand (the script's docstring says why this is a floor only for a hand that follows its recording).",
        "",
        f"* the recorded object moves before the recorded hand touches it in **{len(ahead)} of {len(known)}** "
        f"sequences (median {statistics.median(leads) if leads else 0:.0f} frames ahead, "
        f"max {max(leads) if leads else 0}); {n - len(known)} never show a fingertip within "
        f"{100 * CONTACT_THRESHOLD:.0f} cm",
        f"* floor over all {n}: **E_t {f_t:.2f} cm, E_r {f_r:.2f} deg** against the refined means "
        f"E_t {e_t:.2f} cm, E_r {e_r:.2f} deg ({100 * f_t / e_t:.0f} % and {100 * f_r / e_r:.0f} % of them); "
        f"of it, the frames the object has moved before the touch: E_t {a_t:.2f} cm, E_r {a_r:.2f} deg, the rest "
        "is the recorded pose wandering while the object rests untouched (a simulated object at rest cannot follow it)",
        "",
        "| lead (frames the object moves first) | sequences | floor E_t cm | floor E_r deg | refined E_t cm | "
        "refined E_r deg |",
        "|---|---|---|---|---|---|",
    ]
    bins: list[tuple[str, list[tuple[str, str, Lead, tuple[bool, float, float]]]]] = [
        ("hand first (<= 0)", [r for r in known if (r[2].lead_frames or 0) <= 0]),
        ("1-3", [r for r in known if 1 <= (r[2].lead_frames or 0) <= 3]),
        ("4-9", [r for r in known if 4 <= (r[2].lead_frames or 0) <= 9]),
        (">= 10", [r for r in known if (r[2].lead_frames or 0) >= 10]),
        ("no touch seen", [r for r in rows if r[2].lead_frames is None]),
    ]
    for label, group in bins:
        if group:
            lines.append(f"| {label} | {len(group)} | {mean(r[2].floor_t_cm for r in group):.2f} | "
                         f"{mean(r[2].floor_r_deg for r in group):.2f} | {mean(r[3][1] for r in group):.2f} | "
                         f"{mean(r[3][2] for r in group):.2f} |")
    lines += ["", "Per sequence, largest floor first:", "",
              "| sequence | object | refined | moved | touch | lead | floor E_t cm | floor E_r deg | of it moved E_t | "
              "of it moved E_r | E_t 10+ | E_r 10+ |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for stem, obj, lead, (ok, et, er) in sorted(rows, key=lambda r: -(r[2].floor_t_cm + r[2].floor_r_deg / 4)):
        lines.append(f"| {stem} | {obj} | {'ok' if ok else 'FAIL'} | {lead.moved} | "
                     f"{'-' if lead.touch is None else lead.touch} | "
                     f"{'-' if lead.lead_frames is None else lead.lead_frames} | {lead.floor_t_cm:.2f} | "
                     f"{lead.floor_r_deg:.2f} | {lead.ahead_t_cm:.2f} | {lead.ahead_r_deg:.2f} | {et:.2f} | {er:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = parse_report_args(argv, __doc__.split("\n\n")[0], "reference_lead.md")
    errors = read_errors(args.report)
    sample = load_sample(args, errors, "bench/reference_lead.py")
    if sample is None:
        return 2
    write_report(args, render(args, [(stem, seq.object.name, reference_lead(seq), errors[stem])
                                     for stem, seq in sample]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
