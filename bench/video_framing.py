"""What the video shows and costs (issue #53 item 7): how large the hand is in a panel, and the preview's time.

For one refinement result (default: a DexYCB development sequence refined with the product's options), prints and
writes ``bench/results/video_framing.md``:

* the refined hand's keypoints' extent in pixels at the docs frame (the first where the object has risen 60 % of its
  lift), with the automatic camera and with the close-up, at 320x240 and 640x480 panels;
* the stored preview's wall time (``preview_artifacts``: video, plots, recording, export) at 320x240 and 640x480,
  and at 640x480 with the close-up video (``preview_close_up``), the three alternated ``--rounds`` times after a
  warm-up, and the videos' sizes.

    .venv/bin/python bench/video_framing.py [--result R.npz | --sequence S.npz] [--rounds 3]
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SIZES = ((320, 240), (640, 480))
#: The timed previews: (panel size, with the close-up video).
PREVIEWS = (((320, 240), False), ((640, 480), False), ((640, 480), True))


def main() -> int:
    from worker.visual.gl import prefer_offscreen_backend

    prefer_offscreen_backend()
    import numpy as np

    from common.job_options import JobOptions

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--result", type=Path, default=None, help="a refinement result (default: refine --sequence)")
    parser.add_argument("--sequence", type=Path, default=None, help="DexYCB sequence (default: the docs' one)")
    parser.add_argument("--rounds", type=int, default=3, help="timed rounds per size (default 3)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "video_framing.md")
    args = parser.parse_args()
    if args.result is not None:
        blob = args.result.read_bytes()
    else:
        from bench.docs_pictures import DEFAULT_SEQUENCE
        from common.dexycb import shared_data_dir
        from common.sequence_io import load_sequence
        from worker.refine.run import refine_sequence

        data = shared_data_dir()
        path = args.sequence or (None if data is None else data / "dexycb" / "dev" / DEFAULT_SEQUENCE)
        if path is None:
            print("no ../shared/data: pass --sequence or --result", file=sys.stderr)
            return 2
        blob = refine_sequence(load_sequence(path), JobOptions(), threads=2).to_npz_bytes()

    from worker.visual.framing import View, project
    from worker.visual.playback import resimulate
    from worker.visual.preview import CLOSE_UP, VIDEO, preview_artifacts
    from worker.visual.render import auto_camera

    pb = resimulate(blob)
    z = pb.trajectories["refined"].object_pose[:, 2]
    frame = int(np.argmax(z >= z[0] + 0.6 * (z.max() - z[0])))
    fovy = float(pb.scene.model.vis.global_.fovy)
    machine = f"{platform.node()}, {platform.processor() or platform.machine()}"
    lines = [f"# Video framing and preview cost ({pb.summary.get('sequence')}, frame {frame + 1} of {pb.num_frames})",
             "", f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC, {machine}", "",
             "| view | panel | hand keypoints span (px) | share of the panel |", "|---|---|---|---|"]  # fmt: skip
    for close_up in (False, True):
        for w, h in SIZES:
            cam = auto_camera(pb, size=(w, h), close_up=close_up)
            look = cam.lookat if cam.track is None else cam.track[frame]
            for side, kp in pb.trajectories["refined"].keypoints.items():
                xy = project(kp[frame], View(np.asarray(look), cam.distance, cam.azimuth, cam.elevation), fovy, w / h)
                sx, sy = (xy.max(axis=0) - xy.min(axis=0)) * (w / 2, h / 2)
                view = "close-up" if close_up else "automatic"
                share = 100 * sx * sy / (w * h)
                lines.append(f"| {view} ({side} hand) | {w}x{h} | {sx:.0f} x {sy:.0f} | {share:.1f} % |")
    preview_artifacts(blob, SIZES[0], close_up=True)  # warm-up: imports, the scene's convex parts
    seconds: dict[tuple[tuple[int, int], bool], list[float]] = {p: [] for p in PREVIEWS}
    video_kib: dict[tuple[tuple[int, int], bool], str] = {}
    for _ in range(args.rounds):
        for size, close_up in PREVIEWS:
            t0 = time.perf_counter()
            parts = preview_artifacts(blob, size, close_up=close_up)
            seconds[size, close_up].append(time.perf_counter() - t0)
            video_kib[size, close_up] = " + ".join(str(len(p.data) // 1024) for p in parts
                                                   if p.name in (VIDEO, CLOSE_UP))  # fmt: skip
    lines += ["", "| preview panel | wall s (each round) | median s | video KiB |", "|---|---|---|---|"]
    for (size, close_up), values in seconds.items():
        lines.append(f"| {size[0]}x{size[1]}{' + close-up' if close_up else ''} | "
                     f"{', '.join(f'{v:.2f}' for v in values)} | {float(np.median(values)):.2f} | "
                     f"{video_kib[size, close_up]} |")  # fmt: skip
    text = "\n".join(lines) + "\n"
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
