"""``hoi-refine inspect``, ``hoi-refine replay`` and ``hoi-refine demo`` (issue #2 item 8).

``inspect SEQ`` says what a sequence file holds and whether it validates (exit 2 with the field-named message
when it does not); ``replay SEQ --out RESULT.npz`` runs the raw replay (reference driven, no optimisation)
and prints the metrics; ``demo`` runs the built-in example end to end through a local deployment (``--local``:
refined in-process; ``--raw``: raw replay only). Heavy imports stay inside the handlers.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

#: Metric rows: key, label, unit, format.
_ROWS = (
    ("E_t", "object position error E_t", "cm", "{:.2f}"),
    ("E_r", "object rotation error E_r", "deg", "{:.1f}"),
    ("E_j", "hand joint error E_j", "cm", "{:.2f}"),
    ("E_ft", "fingertip error E_ft", "cm", "{:.2f}"),
    ("max_E_t", "worst-frame position error", "cm", "{:.2f}"),
    ("max_E_r", "worst-frame rotation error", "deg", "{:.1f}"),
    ("paper.E_t", "E_t, paper's protocol (frames 10+)", "cm", "{:.2f}"),
    ("paper.E_r", "E_r, paper's protocol (frames 10+)", "deg", "{:.1f}"),
    ("paper.E_j", "E_j, paper's protocol (frames 10+)", "cm", "{:.2f}"),
    ("paper.E_ft", "E_ft, paper's protocol (frames 10+)", "cm", "{:.2f}"),
    ("paper.success", "success, paper's protocol (frames 10+)", "", "{}"),
    ("penetration_mean_mm", "penetration: mean per-frame maximum", "mm", "{:.2f}"),
    ("penetration_max_mm", "penetration: sequence maximum", "mm", "{:.2f}"),
    ("hand_only_fraction", "lifted frames held by the hand alone", "%", "{:.0%}"),
)


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "inspect", help="show what a sequence file holds and whether it is valid", description=__doc__
    )
    p.add_argument("sequence", type=Path, help="sequence file (.npz native or DexYCB, .json, DexYCB folder)")
    p.set_defaults(func=cmd_inspect)

    r = subparsers.add_parser(
        "replay",
        help="raw replay: drive the hand along the retargeted reference (no optimisation) and report metrics",
        description="Retarget the hand, simulate the object from its rest pose, write trajectory + contacts.",
    )
    src = r.add_mutually_exclusive_group(required=True)
    src.add_argument("sequence", type=Path, nargs="?", help="sequence file")
    src.add_argument("--example", action="store_true", help="use the built-in synthetic grasp-and-lift")
    r.add_argument("--out", type=Path, default=None, help="result file to write (.npz)")
    r.set_defaults(func=cmd_replay)

    d = subparsers.add_parser(
        "demo",
        help="run the built-in example end to end (no data or licence needed)",
        description=(
            "By default: start `hoi-refine up --workers 2` (API + local Ray + 2 workers, SQLite under var/), "
            "submit the built-in grasp-and-lift over HTTP, follow its progress, print raw vs refined metrics and "
            "save the result and contacts under --out-dir, then stop the deployment. --local refines in this "
            "process instead (no server); --raw only replays the observation without optimisation."
        ),
    )
    mode = d.add_mutually_exclusive_group()
    mode.add_argument("--local", action="store_true", help="refine in this process, without the service")
    mode.add_argument("--raw", action="store_true", help="only the raw replay, no refinement")
    d.add_argument("--api", default=None, help="use this running service instead of starting one (with --key)")
    d.add_argument("--key", default=None, help="API key for --api")
    d.add_argument("--out-dir", type=Path, default=Path("var/demo"), help="where the service demo saves files")
    d.add_argument("--out", type=Path, default=None, help="with --raw: also write the raw-replay result (.npz)")
    d.set_defaults(func=cmd_demo)


def _describe(seq: Any) -> list[tuple[str, str]]:
    obj = seq.object
    shape = (
        f"{obj.primitive} {[round(float(s), 4) for s in obj.size]}"
        if obj.primitive
        else f"mesh, {len(obj.mesh_vertices)} vertices, {len(obj.mesh_faces)} faces"
    )
    rows = [
        ("name", seq.name),
        ("frames", f"{seq.num_frames} at {seq.fps:g} fps ({seq.num_frames / seq.fps:.2f} s), first {seq.frame_start}"),
        ("object", f"{obj.name}: {shape}, {obj.mass_kg:g} kg"),
        ("world frame", "world_from_camera given" if seq.world_from_source is not None else "from up vector / default"),
    ]
    for h in seq.hands:
        parts = [f"{int(h.valid.sum())}/{len(h.valid)} valid frames"]
        if h.keypoints is not None:
            parts.append("21 keypoints")
        if h.mano is not None:
            parts.append(f"MANO ({h.mano.pose_format}, {h.mano.hand_pose.shape[1]} pose values)")
        rows.append((f"{h.side} hand", ", ".join(parts)))
    pose = seq.object_pose_world()
    lift = 100 * (pose[:, 2].max() - pose[0, 2])
    rows.append(("object lift", f"{lift:.1f} cm above its frame-0 height at most"))
    for key, value in sorted(seq.meta.items()):
        rows.append((f"meta.{key}", value))
    return rows


def cmd_inspect(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from common.errors import SequenceValidationError
    from common.sequence_io import load_sequence
    from common.settings import get_settings

    console = Console()
    try:
        seq = load_sequence(args.sequence, max_frames=get_settings().max_frames)
    except SequenceValidationError as exc:
        console.print(f"[bold red]invalid[/] {args.sequence}")
        for problem in exc.problems:
            console.print(f"  {problem}")
        raise
    table = Table(title=str(args.sequence), show_header=False)
    for key, value in _describe(seq):
        table.add_row(key, value)
    console.print(table)
    _check_mano(seq, console)
    console.print("[bold green]valid[/]: every field passed validation")
    return 0


def _check_mano(seq: Any, console: Any) -> None:
    """MANO-only hands cannot run without the model files: say so, then raise the error that names
    ``HOI_REFINE_MANO_DIR`` (``common.cli.main`` prints it and exits 2). No torch is imported."""
    from common.errors import ManoModelMissingError
    from worker.mano import mano_available, require_mano_models

    try:
        require_mano_models(seq)
    except ManoModelMissingError:
        console.print("[bold red]cannot run[/]: a hand is given only as MANO parameters and the MANO model is missing")
        raise
    sides = [h.side for h in seq.hands if h.mano is not None]
    if sides and mano_available(sides):
        console.print(f"MANO model found for the {' and '.join(sides)} hand: the MANO hand is used")


def metrics_table(title: str, columns: dict[str, dict[str, Any]]) -> Any:
    """A rich table of metrics, one column per run (e.g. {"raw": metrics})."""
    from rich.table import Table

    table = Table(title=title)
    table.add_column("metric")
    table.add_column("unit")
    for name in columns:
        table.add_column(name, justify="right")
    for key, label, unit, fmt in _ROWS:
        values = [_lookup(m, key) for m in columns.values()]
        table.add_row(label, unit, *(fmt.format(v) if v is not None else "-" for v in values))
    table.add_row("success (every frame E_t<=3 cm, E_r<=30 deg)", "", *(str(m["success"]) for m in columns.values()))
    return table


def _lookup(metrics: dict[str, Any], key: str) -> Any:
    """``metrics[key]``, a dotted key reading a nested block (``paper.E_t``); None when absent."""
    value: Any = metrics
    for part in key.split("."):
        if not isinstance(value, dict) or part not in value:
            return None
        value = value[part]
    return value


def _run_replay(seq: Any, out: Path | None) -> Any:
    from rich.console import Console

    from worker.replay import raw_replay, replay_result_bytes

    console = Console()
    with console.status(f"raw replay of {seq.name} ({seq.num_frames} frames)..."):
        result = raw_replay(seq)
    console.print(metrics_table(f"raw replay: {seq.name}", {"raw": result.metrics}))
    t = result.timings
    ik = ", ".join(f"{side} {v:.2f} mm" for side, v in result.ik_residual_mm().items())
    console.print(
        f"IK residual (mean over valid frames): {ik}; {result.steps} simulated steps; "
        f"retarget {t['retarget_s']:.2f} s, scene {t['build_scene_s']:.2f} s, simulate {t['simulate_s']:.2f} s "
        f"({t['steps_per_second']:.0f} steps/s); {len(result.contacts['contact_frame'])} contacts recorded"
    )
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(replay_result_bytes(result))
        console.print(f"wrote {out}")
    return result


def cmd_replay(args: argparse.Namespace) -> int:
    from common.sequence_io import load_sequence
    from common.settings import get_settings

    if args.example:
        from worker.example import example_sequence

        seq = example_sequence()
    else:
        seq = load_sequence(args.sequence, max_frames=get_settings().max_frames)
    _run_replay(seq, args.out)
    return 0


def _free_port() -> int:
    """A port the OS says is free now, so the demo does not collide with a server already on 8000."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def cmd_demo(args: argparse.Namespace) -> int:
    if args.local:
        from worker.cli_refine import run_demo as run_local_demo

        return int(run_local_demo())
    if not args.raw:
        from worker.runtime.demo_client import run_demo as run_service_demo

        if args.api:
            return run_service_demo(base_url=args.api, api_key=args.key, out_dir=args.out_dir)
        return run_service_demo(out_dir=args.out_dir, port=_free_port())
    from rich.console import Console

    from worker.example import example_sequence

    console = Console()
    console.print(
        "[bold]hoi-refine demo[/]: the built-in synthetic grasp-and-lift (a right hand pinches a 0.2 kg box and "
        "lifts it 20 cm in 2.4 s; the observed hand has hovering/penetrating fingers and jitter). Raw replay: "
        "the simulated hand follows the retargeted observation with no optimisation; the object moves only "
        "through contact."
    )
    _run_replay(example_sequence(), args.out)
    return 0
