"""How fast the ARCTIC recordings move their objects, against DexYCB: evidence for why a sequence fails (issue #52).

    .venv/bin/python bench/arctic_recordings.py --arctic DIR [--results DIR] [--out FILE]

Reads every usable dexmachina-processed ARCTIC sequence (``bench/arctic.py``'s ``usable_sequences``; the ARCTIC
licence forbids copying them into this project) and prints, from the recording alone: how many frames turn the
object faster than 5 and 10 deg per frame, its fastest turn and move, the mean turn per 50 frames and the fastest
such mean over any 50 frames, the hinge's range and speed, and how deep the recorded fingers lie inside the base
part's collision geometry; then the product's recording-only outcome reasons (``worker.refine.outcome``). A
reference row gives the same figures over the DexYCB ``--dexycb-sample`` (median, p90 and maximum over its
sequences; left out when ``../shared/data`` is missing). With ``--results`` (``bench/arctic.py``'s result folder),
each sequence whose refined result is there also gets its first frame past a success limit and the recording's mean
turn over the 30 frames before it. Last, the DexYCB sequences refined by ``bench/tail_sample.py`` (its archive) are
binned by their fastest 50-frame mean turn, with their success rate, attempts and wall time: how hard a sustained turn
is for one hand, where the method is known to work.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import sys
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.arctic import first_failure, result_name, usable_sequences  # noqa: E402
from bench.provenance import provenance_line  # noqa: E402
from bench.refine import code_digest  # noqa: E402
from common.sequence import Sequence  # noqa: E402

#: Turn speeds (deg per frame at 30 fps) the table counts frames above: 5 is about the fastest a DexYCB sequence
#: sustains for more than a few frames, 10 is past nearly all of DexYCB's frames.
TURN_LEVELS = (5.0, 10.0)
BLOCK = 50  # frames per block of the turn profile
LEAD = 30  # frames before a first failure whose mean turn is reported
TURN_BINS = (0.0, 2.0, 3.0, 4.0, 5.0, 8.0, 12.0)  # sustained-turn bins (deg per frame) of the DexYCB table


@dataclass
class Motion:
    """One recording's object motion, per frame step, in units at 30 fps."""

    turn_deg: np.ndarray  # (F-1,) object rotation between consecutive frames
    move_cm: np.ndarray  # (F-1,) object translation between consecutive frames
    hinge_deg: np.ndarray | None  # (F, J) revolute joint values; None for a rigid object

    @classmethod
    def of(cls, seq: Sequence) -> Motion:
        from worker.refine.outcome import recording_steps

        turn, move = recording_steps(seq.object_pose_world())
        rate = float(seq.fps) / 30.0
        hinge = None
        if seq.articulation is not None and seq.object.joints:
            scale = np.array([j.display_scale() for j in seq.object.joints])
            hinge = np.asarray(seq.articulation) * scale
        return cls(turn * rate, move * rate, hinge)

    def frames_over(self, deg: float) -> int:
        return int(np.sum(self.turn_deg > deg))

    def sustained_turn(self) -> float:
        """The fastest mean turn over any ``BLOCK`` consecutive frame steps (deg per frame)."""
        if len(self.turn_deg) < BLOCK:
            return float(self.turn_deg.mean())
        return float(np.convolve(self.turn_deg, np.ones(BLOCK) / BLOCK, mode="valid").max())


def sequence_row(path: Path, results: Path | None, cache_dir: Path) -> list[str]:
    """The table cells of one ARCTIC sequence."""
    from common.job_options import JobOptions
    from common.sequence_io import load_sequence
    from worker.refine import outcome
    from worker.refine.prepare import prepare

    seq = load_sequence(path)
    m = Motion.of(seq)
    prep = prepare(seq, JobOptions(), cache_dir=cache_dir)
    depth_mm, depth_frame = outcome.recorded_depth(prep)
    reasons = [r for r in (outcome.recording_too_fast(prep), outcome.fingers_through_object(prep),
                           outcome.unsupported_start(prep, cache_dir), outcome.hand_sparse(prep)) if r is not None]
    hinge = "-"
    if m.hinge_deg is not None:
        step = np.abs(np.diff(m.hinge_deg, axis=0)).max(axis=1)
        hinge = (f"{m.hinge_deg.min():.0f}..{m.hinge_deg.max():.0f} / {step.max():.1f} / "
                 f"{int(np.sum(step > TURN_LEVELS[0]))}")
    profile = " ".join(f"{m.turn_deg[i:i + BLOCK].mean():.1f}" for i in range(0, len(m.turn_deg), BLOCK))
    fail = "-"
    if results is not None:
        result = results / result_name(f"{path.parent.name}/{path.stem}", "per_hand")
        f, fail = first_failure(result)
        if f is not None:
            fail += f"; turn before it {m.turn_deg[max(0, f - LEAD):f].mean():.1f} deg/frame"
    why = "; ".join(f"{r.code.value} at frame {r.frame} ({r.value} {r.unit})" for r in reasons) or "none"
    k = int(np.argmax(m.turn_deg))
    return [f"{path.parent.name}/{path.stem}", str(seq.num_frames), *(str(m.frames_over(d)) for d in TURN_LEVELS),
            f"{m.turn_deg[k]:.1f} ({k + 1})", f"{m.sustained_turn():.1f}", f"{m.move_cm.max():.2f}", hinge,
            f"{depth_mm:.1f} ({depth_frame})", why, fail, profile]


def dexycb_row(sample: str) -> list[str] | None:
    """Median / p90 / max over a DexYCB sample of the same figures; None when the data are missing."""
    from bench.samples.draw import read_sample
    from bench.tail import DATA

    listing = ROOT / "bench" / "samples" / f"{sample}.txt"
    if not DATA.is_dir():
        return None
    motions = [dexycb_motion(file.removesuffix(".npz")) for file, _ in read_sample(listing)]

    def spread(values: list[float], digits: int = 0) -> str:
        v = np.asarray(values)
        return f"{np.median(v):.{digits}f} / {np.percentile(v, 90):.{digits}f} / {v.max():.{digits}f}"

    return [f"DexYCB {sample} ({len(motions)}; median / p90 / max)", "-",
            *(spread([m.frames_over(d) for m in motions]) for d in TURN_LEVELS),
            spread([float(m.turn_deg.max()) for m in motions], 1), spread([m.sustained_turn() for m in motions], 1),
            spread([float(m.move_cm.max()) for m in motions], 2), "-", "-", "-", "-", "-"]


@functools.cache
def dexycb_motion(stem: str) -> Motion:
    """A DexYCB dev sequence's motion, read once for the reference row and the bins both."""
    from bench.tail import DATA
    from common.sequence_io import load_sequence

    return Motion.of(load_sequence(DATA / f"{stem}.npz"))


def turn_bins(archive: Path) -> list[str]:
    """The archived DexYCB refinements (whole plan) binned by sustained turn; empty when either is missing."""
    from bench.tail import DATA

    if not archive.is_file() or not DATA.is_dir():
        return []
    rows = [json.loads(line) for line in archive.read_text().splitlines() if line.strip()]
    runs = [(dexycb_motion(r["sequence"]).sustained_turn(), r) for r in rows
            if r["mode"] == "full" and (DATA / f"{r['sequence']}.npz").is_file()]
    lines = [f"DexYCB sequences refined by the whole plan (`{archive.relative_to(ROOT)}`), by their fastest "
             f"{BLOCK}-frame mean turn:", "",
             "| turn deg/frame | sequences | SR % | mean attempts | median wall s |", "|---|---|---|---|---|"]
    for lo, hi in itertools.pairwise(TURN_BINS):
        sel = [r for turn, r in runs if lo <= turn < hi]
        if sel:
            lines.append(f"| {lo:g}-{hi:g} | {len(sel)} | {100 * np.mean([r['success'] for r in sel]):.0f} | "
                         f"{np.mean([r['attempts'] for r in sel]):.1f} | {np.median([r['wall_s'] for r in sel]):.0f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--arctic", type=Path, required=True,
                   help="dexmachina's assets/arctic folder (processed/<subject>/*.npy and one folder per object)")
    p.add_argument("--results", type=Path, default=None,
                   help="bench/arctic.py's result folder: adds each refined result's first frame past a limit")
    p.add_argument("--dexycb-sample", default="dev120", help="the DexYCB sample of the reference row")
    p.add_argument("--tail-archive", type=Path, default=ROOT / "bench" / "results" / "tail_sample_runs.jsonl",
                   help="bench/tail_sample.py's archive of DexYCB refinements, binned by sustained turn")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "arctic_recordings.md")
    args = p.parse_args(argv)
    paths = usable_sequences(args.arctic)
    if not paths:
        p.error(f"no usable sequence under {args.arctic} (expected processed/<subject>/*.npy and object folders)")
    head = ["sequence", "frames", *(f"frames turning > {d:g} deg" for d in TURN_LEVELS), "fastest turn deg (frame)",
            f"fastest {BLOCK}-frame mean turn deg", "fastest move cm",
            "hinge range deg / fastest deg per frame / frames > 5", "finger depth mm (frame)",
            "recording-only reasons", "refined: first frame past a limit", f"mean turn deg/frame per {BLOCK} frames"]
    rows = [sequence_row(path, args.results, ROOT / "var" / "cache") for path in paths]
    ref = dexycb_row(args.dexycb_sample)
    lines = [
        "# How fast the ARCTIC recordings move their objects (bench/arctic_recordings.py)", "",
        f"Written {datetime.now(UTC):%Y-%m-%d %H:%M} UTC. {provenance_line(code_digest())} Figures from the recordings "
        "alone, per frame step at 30 fps. Finger depth: the deepest recorded finger keypoint inside the base part's "
        "collision geometry at the recorded pose.", "",
        "| " + " | ".join(head) + " |", "|" + "---|" * len(head),
        *("| " + " | ".join(r) + " |" for r in rows),
        *([] if ref is None else ["| " + " | ".join(ref) + " |"]),
    ]
    bins = turn_bins(args.tail_archive)
    lines += ["", *bins] if bins else []
    text = "\n".join(lines) + "\n"
    args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
