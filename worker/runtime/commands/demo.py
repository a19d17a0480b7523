"""``hoi-refine demo``: the built-in example end to end, with no data and no MANO licence (``make demo``).

By default through a local deployment (``hoi-refine up`` in a child process, the example submitted over HTTP:
``worker.runtime.demo_client``); ``--local`` refines in this process, ``--raw`` only replays the observation.
``--example`` picks the built-in example (``worker.example.catalogue``): the one-hand box by default, or the
two-handed hinged box.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    d = subparsers.add_parser(
        "demo",
        help="run the built-in example end to end (no data or licence needed)",
        description=(
            "By default: start `hoi-refine up --workers 2` (API + local Ray + 2 workers, SQLite under var/), "
            "submit the built-in grasp-and-lift over HTTP, follow its progress, print raw vs refined metrics and "
            "save the result, contacts, preview video and plots under --out-dir, then stop the deployment. --local "
            "refines in this process instead (no server); --raw only replays the observation without optimisation."
        ),
    )
    mode = d.add_mutually_exclusive_group()
    mode.add_argument("--local", action="store_true", help="refine in this process, without the service")
    mode.add_argument("--raw", action="store_true", help="only the raw replay, no refinement")
    d.add_argument("--api", default=None, help="use this running service instead of starting one (with --key)")
    d.add_argument("--key", default=None, help="API key for --api")
    d.add_argument("--out-dir", type=Path, default=Path("var/demo"),
                   help="where the demo saves the result, contacts, video and plots (default var/demo)")  # fmt: skip
    d.add_argument("--out", type=Path, default=None, help="with --raw: also write the raw-replay result (.npz)")
    d.add_argument("--example", choices=("box", "hinged_box"), default="box",
                   help="the built-in example: box (one hand lifts a box; the default) or hinged_box (two hands, one "
                   "holding a box while the other opens its hinged block)")  # fmt: skip
    d.set_defaults(func=cmd_demo)


def _free_port() -> int:
    """A port the OS says is free now, so the demo does not collide with a server already on 8000."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def cmd_demo(args: argparse.Namespace) -> int:
    if args.local:
        return run_local_demo(out_dir=args.out_dir, example=args.example)
    if not args.raw:
        from worker.runtime.demo_client import run_demo as run_service_demo

        if args.api:
            return run_service_demo(base_url=args.api, api_key=args.key, out_dir=args.out_dir, example=args.example)
        return run_service_demo(out_dir=args.out_dir, port=_free_port(), example=args.example)
    from rich.console import Console

    from worker.commands.replay import run_replay
    from worker.example.catalogue import example_named

    example = example_named(args.example)
    console = Console()
    console.print(
        f"[bold]hoi-refine demo[/]: {example.description}. Raw replay: the simulated hands follow the retargeted "
        "observation with no optimisation; the object moves only through contact."
    )
    run_replay(example.build(), args.out)
    return 0


def run_local_demo(threads: int = 2, short: bool = False, out_dir: Path | str = Path("var/demo"), example: str = "box",
                   options: Any = None) -> int:
    """Refine the built-in example ``example`` in this process (``options``: ``JobOptions``, default the
    product's), print raw vs refined, and save the result, its video and its plots under ``out_dir`` (``hoi-refine
    demo --local``)."""
    from common.job_options import JobOptions
    from common.settings import get_settings
    from worker.commands.progress import ProgressBar
    from worker.commands.refine import print_refine_metrics
    from worker.example.catalogue import example_named
    from worker.refine.run import refine_sequence
    from worker.visual import render_video, resimulate, write_plots

    chosen = example_named(example)
    seq = chosen.build_short() if short else chosen.build()
    options = options or JobOptions()
    bar = ProgressBar(options.restarts, options.polish)
    cache_dir = get_settings().resolved_cache_dir()
    outcome = refine_sequence(seq, options, threads=threads, progress=bar, cache_dir=cache_dir)
    bar.finish()
    print(f"refined the built-in example {seq.name!r} ({seq.num_frames} frames)")
    print_refine_metrics(outcome.summary)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    blob = outcome.to_npz_bytes()
    result, video = out / f"{seq.name}.result.npz", out / f"{seq.name}.mp4"
    result.write_bytes(blob)
    render_video(resimulate(blob, cache_dir=cache_dir), str(video))
    plots = write_plots(blob, out / f"{seq.name}_plots")
    print(f"result: {result}\nvideo: {video}\nplots: {', '.join(str(p) for p in plots)}")
    return 0
