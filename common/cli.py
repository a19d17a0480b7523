"""``hoi-refine``: one command, subcommands registered by the packages that own them.

Each module in ``SUBCOMMAND_MODULES`` exposes ``register(subparsers)`` and keeps heavy imports (MuJoCo,
Ray, FastAPI) inside its handlers, so ``hoi-refine --help`` stays fast. Handlers take the parsed
namespace and return an exit code. Project errors print one clear line and exit 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from common.errors import HoiRefineError

#: Modules that add subcommands (each has ``register(subparsers)``).
SUBCOMMAND_MODULES: tuple[str, ...] = (
    "worker.cli_local",
    "worker.cli_refine",
    "service.submit.cli",
    "worker.cli_runtime",
    "service.cli",
    "worker.visual.cli",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hoi-refine",
        description=(
            "Turn vision-aligned hand-object demonstrations into physically executable trajectories: "
            "an articulated hand is driven in MuJoCo, the object moves only through contact, and the hand "
            "motion is optimised with CMA-ES until the simulated object follows the recorded one."
        ),
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # usage errors and --help: return argparse's code, so main() always returns
        return int(exc.code or 0) if not isinstance(exc.code, str) else 2
    try:
        return int(args.func(args) or 0)
    except HoiRefineError as exc:
        print(f"hoi-refine: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hoi-refine: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
