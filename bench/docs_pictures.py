"""The README's pictures of a real DexYCB refinement: one frame of its rendered video and its error plot.

Refines one DexYCB development sequence (or takes a result file), renders the video as `hoi-refine render`
does, and writes ``docs/dexycb_frame.png`` (the first frame where the simulated object has risen 60% of its lift),
``docs/dexycb_closeup.png`` (that frame as `hoi-refine render --close-up` draws it) and ``docs/dexycb_errors.png``
(the ``errors.png`` plot). The dashboard screenshot comes from the browser test
(``HOI_REFINE_UPDATE_DOCS=1``, tests/acceptance/test_dashboard_browser.py).

    .venv/bin/python bench/docs_pictures.py [--sequence PATH | --result PATH] [--prefix NAME]
    .venv/bin/python bench/docs_pictures.py --arctic RESULT [--frame F] [--camera AZIMUTH,ELEVATION,DISTANCE]

``--prefix allegro --result R.npz`` writes ``docs/allegro_frame.png`` / ``_closeup.png`` / ``_errors.png`` from a
robot hand's result (issue #55: ``hoi-refine refine SEQ --hand allegro --robot-dir DEX_URDF``, the default
sequence).

``--arctic`` takes a refinement result of an ARCTIC sequence (``bench/arctic.py`` writes them under var/arctic/)
and writes ``docs/arctic_frame.png``: the refined replay at frame F (default: the frame where the joint is
opened furthest from its start), the camera looking at the simulated object from the given direction.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DEFAULT_SEQUENCE = "20200709-subject-01__20200709_141754.npz"


def main() -> int:
    from worker.visual.gl import prefer_offscreen_backend

    prefer_offscreen_backend()
    from common.dexycb import shared_data_dir
    from common.job_options import JobOptions

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequence", type=Path, default=None, help="DexYCB development NPZ to refine")
    parser.add_argument("--result", type=Path, default=None, help="an existing refinement result instead")
    parser.add_argument("--out", type=Path, default=ROOT / "docs", help="folder for the pictures (default docs/)")
    parser.add_argument("--prefix", default="dexycb", help="file name prefix (default dexycb)")
    parser.add_argument("--arctic", type=Path, default=None, help="an ARCTIC refinement result: docs/arctic_frame.png")
    parser.add_argument("--frame", type=int, default=None, help="with --arctic: the frame (0-based)")
    parser.add_argument("--camera", default="210,-20,0.5", help="with --arctic: AZIMUTH,ELEVATION,DISTANCE")
    args = parser.parse_args()
    if args.arctic is not None:
        return arctic_frame(args.arctic, args.out, args.frame, args.camera)
    if args.result is not None:
        blob = args.result.read_bytes()
    else:
        path = args.sequence
        if path is None:
            data = shared_data_dir()
            if data is None:
                print("no ../shared/data: pass --sequence or --result", file=sys.stderr)
                return 2
            path = data / "dexycb" / "dev" / DEFAULT_SEQUENCE
        from common.sequence_io import load_sequence
        from worker.refine.run import refine_sequence

        blob = refine_sequence(load_sequence(path), JobOptions(), threads=2).to_npz_bytes()
    import numpy as np
    from PIL import Image

    from worker.visual import read_mp4, render_video, resimulate, write_plots
    from worker.visual.render import auto_camera, render_frames

    pb = resimulate(blob)
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        video = Path(tmp) / "dexycb.mp4"
        render_video(pb, str(video), ("raw", "refined"))  # the default panels and camera, as `hoi-refine render`
        frames, _ = read_mp4(video)
        z = pb.trajectories["refined"].object_pose[:, 2]
        best = int(np.argmax(z >= z[0] + 0.6 * (z.max() - z[0])))  # well into the lift
        Image.fromarray(frames[best]).save(args.out / f"{args.prefix}_frame.png")
        close_up = auto_camera(pb, close_up=True)
        closeup = next(render_frames(pb, ["raw", "refined"], camera=close_up, frames=[best]))
        Image.fromarray(closeup).save(args.out / f"{args.prefix}_closeup.png")
        plots = write_plots(blob, Path(tmp) / "plots")
        shutil.copy(next(p for p in plots if p.name == "errors.png"), args.out / f"{args.prefix}_errors.png")
    print(f"wrote {args.out / (args.prefix + '_frame.png')}, {args.prefix}_closeup.png (frame {best + 1} of "
          f"{pb.num_frames}) and {args.out / (args.prefix + '_errors.png')} ({pb.summary.get('sequence')})")
    return 0


def arctic_frame(result: Path, out: Path, frame: int | None, camera: str) -> int:
    """The refined replay of an ARCTIC result at ``frame``, seen from ``camera`` around the simulated object."""
    import numpy as np
    from PIL import Image

    from worker.visual import resimulate
    from worker.visual.render import parse_camera, render_frames

    pb = resimulate(result.read_bytes())
    refined = pb.trajectories["refined"]
    if frame is None:
        assert refined.articulation is not None
        frame = int(np.argmax(np.abs(refined.articulation - refined.articulation[0]).max(axis=1)))
    x, y, z = refined.object_pose[frame, :3]
    cam = parse_camera(f"{camera},{x},{y},{z}", pb)
    out.mkdir(parents=True, exist_ok=True)
    Image.fromarray(next(render_frames(pb, ["refined"], 640, 480, cam, [frame]))).save(out / "arctic_frame.png")
    print(f"wrote {out / 'arctic_frame.png'} (frame {frame + 1} of {pb.num_frames}, {pb.summary.get('sequence')})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
