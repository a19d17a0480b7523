"""``hoi-refine render | view | plot | export``: see, plot and take away a refinement result (issue #18).

Each command is a ``hoi_refine.commands`` entry point (``register_render`` etc.; pyproject.toml). Heavy imports
stay inside the handlers so ``hoi-refine --help`` stays fast; the render commands choose the offscreen OpenGL
backend before MuJoCo is imported (``worker.visual.gl``).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

RESULT_HELP = ("result file written by `hoi-refine refine` or downloaded from the service (.npz); a raw replay "
               "from `hoi-refine replay` works too, with --sequence")
SEQUENCE_HELP = "the sequence file the result was made from (default: the one a refinement result embeds)"


def register_render(subparsers: Any) -> None:
    r = subparsers.add_parser(
        "render",
        help="render a result to an MP4: raw replay and refined side by side",
        description="Re-simulates the result's raw replay and refined controls (as `verify` does) and renders "
        "every frame offscreen with MuJoCo (EGL; set MUJOCO_GL=osmesa where EGL is missing): the simulated hand "
        "and object, the recorded object as a translucent green ghost, red arrows of the hand's force on the object "
        "at each contact (1 cm per newton, at most 8 cm) and the frame number with that frame's E_t / E_r.",
    )
    r.add_argument("result", type=Path, help=RESULT_HELP)
    r.add_argument("--out", type=Path, default=None, help="video file to write (default: RESULT.mp4 beside it)")
    r.add_argument("--which", choices=("both", "raw", "refined"), default="both",
                   help="panels: both side by side (default; a raw replay has only raw), or one")  # fmt: skip
    r.add_argument("--size", default="640x480", help="size of one panel, WIDTHxHEIGHT (default 640x480)")
    r.add_argument(
        "--camera", default="auto",
        help="auto (frames the hands and object over the sequence; default), a camera name of the scene, "
        "AZIMUTH,ELEVATION (auto distance), or AZIMUTH,ELEVATION,DISTANCE[,X,Y,Z] (degrees, metres; X,Y,Z the point "
        "looked at)",
    )  # fmt: skip
    r.add_argument("--close-up", action="store_true",
                   help="a close-up: the camera follows the recorded object and frames it with the fingers at it "
                   "(with --camera auto or AZIMUTH,ELEVATION)")  # fmt: skip
    r.add_argument("--sequence", type=Path, default=None, help=SEQUENCE_HELP)
    r.set_defaults(func=_render)


def register_view(subparsers: Any) -> None:
    v = subparsers.add_parser(
        "view",
        help="write a Rerun recording (.rrd) of a result, or open it in the Rerun viewer",
        description="Logs the re-simulated raw replay and refined run to Rerun: hand and object geometry per frame, "
        "the recorded object and hand, contacts with force arrows, and per-frame errors and per-finger contact "
        "force on the `frame` timeline. Open the file with `rerun FILE.rrd`.",
    )
    v.add_argument("result", type=Path, help=RESULT_HELP)
    v.add_argument("--out", type=Path, default=None, help="recording to write (default: RESULT.rrd beside it)")
    v.add_argument("--spawn", action="store_true", help="also start the Rerun viewer (needs a display)")
    v.add_argument("--sequence", type=Path, default=None, help=SEQUENCE_HELP)
    v.set_defaults(func=_view)


def register_plot(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "plot",
        help="PNG plots of a result: errors per frame, contact force per finger, loss history",
        description="errors.png (E_t, E_r raw vs refined with the success limits), contact_forces.png (per "
        "finger) and, for refinements, loss_history.png (best loss per CMA-ES generation per window). Reads the "
        "result file only: no simulation.",
    )
    p.add_argument("result", type=Path, help=RESULT_HELP.replace(", with --sequence", ""))
    p.add_argument("--out", type=Path, default=None, help="folder to write into (default: RESULT_plots/ beside it)")
    p.set_defaults(func=_plot)


def register_export(subparsers: Any) -> None:
    e = subparsers.add_parser(
        "export",
        help="a self-contained folder: MJCF scene, controls, trajectories and a replay script (mujoco + numpy)",
        description="Writes scene.xml (the exact MJCF and physics settings), controls.npz (per physics step, "
        "interpolated), trajectories.npz, contacts.npz, export.json and replay.py, a script that needs only "
        "mujoco and numpy: `python replay.py` in the folder replays the controls and prints the object error "
        "against the stored trajectory.",
    )
    e.add_argument("result", type=Path, help=RESULT_HELP)
    e.add_argument("--out", type=Path, default=None, help="folder to write (default: RESULT_export/ beside it)")
    e.add_argument("--sequence", type=Path, default=None, help=SEQUENCE_HELP)
    e.set_defaults(func=_export)


def _folders() -> dict[str, Any]:
    """The configured convex-decomposition cache and MANO folder (``HOI_REFINE_*``), as ``verify`` passes them."""
    from common.settings import get_settings

    settings = get_settings()
    return {"cache_dir": settings.resolved_cache_dir(), "mano_dir": settings.mano_dir}


def _beside(result: Path, suffix: str) -> Path:
    return result.with_name(result.stem + suffix)


def _sequence(args: argparse.Namespace) -> Any:
    if args.sequence is None:
        return None
    from common.sequence_io import load_sequence

    return load_sequence(args.sequence)


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 640x480") from None
    if w < 16 or h < 16 or w % 2 or h % 2:
        raise argparse.ArgumentTypeError(f"--size {text!r}: width and height must be even and at least 16")
    return w, h


def _render(args: argparse.Namespace) -> int:
    from worker.visual.gl import prefer_offscreen_backend

    prefer_offscreen_backend()
    from common.errors import InvalidRequestError
    from worker.visual.playback import load_result, resimulate
    from worker.visual.render import parse_camera, render_video

    try:
        width, height = parse_size(args.size)
    except argparse.ArgumentTypeError as exc:
        raise InvalidRequestError.single("size", str(exc)) from None
    which = None if args.which == "both" else (args.which,)
    pb = resimulate(load_result(args.result), _sequence(args), which=which, **_folders())
    panels = list(pb.trajectories)
    try:
        camera = parse_camera(args.camera, pb, (width, height), close_up=args.close_up)
    except ValueError as exc:
        raise InvalidRequestError.single("camera", str(exc)) from None
    out = args.out or _beside(args.result, ".mp4")
    n = render_video(pb, str(out), panels, width, height, camera)
    print(f"wrote {out} ({n} frames, {' | '.join(panels)}, {width * len(panels)}x{height}, {pb.fps:g} fps)")
    return 0


def _view(args: argparse.Namespace) -> int:
    from worker.visual.playback import load_result, resimulate
    from worker.visual.rerun_log import write_recording

    pb = resimulate(load_result(args.result), _sequence(args), **_folders())
    out = args.out or _beside(args.result, ".rrd")
    write_recording(pb, out, spawn=args.spawn)
    print(f"wrote {out} (open it with `rerun {out}`)")
    return 0


def _plot(args: argparse.Namespace) -> int:
    from worker.visual.playback import load_result
    from worker.visual.plots import write_plots

    out = args.out or _beside(args.result, "_plots")
    for path in write_plots(load_result(args.result), out):
        print(f"wrote {path}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from worker.visual.export import export_result
    from worker.visual.playback import load_result

    out = args.out or _beside(args.result, "_export")
    export_result(load_result(args.result), out, _sequence(args), **_folders())
    print(f"wrote {out}/ (replay it anywhere with `python {out / 'replay.py'}`: needs only mujoco and numpy)")
    return 0
