"""``hoi-refine``: one command; its subcommands are registered by the packages that own them.

Every subcommand is an entry point in the ``hoi_refine.commands`` group (pyproject.toml): the name is the
subcommand, the value a ``register(subparsers)`` function in the module that holds its code. That is the one
way ``main`` finds a command, and it keeps this bottom layer free of imports of ``worker`` and ``service``
(import-linter checks it). Command modules keep heavy imports (MuJoCo, Ray, FastAPI) inside their handlers, so
``hoi-refine --help`` stays fast. Handlers take the parsed namespace and return an exit code; project errors
print one clear line and exit 2.
"""

from __future__ import annotations

import argparse
import sys
from importlib.metadata import entry_points

from common.errors import ConfigurationError, HoiRefineError

#: The entry-point group that names every subcommand.
COMMAND_GROUP = "hoi_refine.commands"
#: The order subcommands are listed in ``--help``: the science a user starts with, then the service.
HELP_ORDER = (
    "inspect", "replay", "refine", "verify", "render", "view", "plot", "export", "demo", "submit", "up", "serve",
    "worker", "ray-head", "keys", "dataset",
)  # fmt: skip


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
    commands = {ep.name: ep for ep in entry_points(group=COMMAND_GROUP)}
    if not commands:
        raise ConfigurationError(
            f"no {COMMAND_GROUP!r} entry points: hoi-refine is not installed (pip install -e . in the checkout)"
        )
    rank = {name: i for i, name in enumerate(HELP_ORDER)}
    for name in sorted(commands, key=lambda n: (rank.get(n, len(rank)), n)):
        commands[name].load()(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        parser = build_parser()
    except HoiRefineError as exc:
        print(f"hoi-refine: error: {exc}", file=sys.stderr)
        return 2
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # usage errors and --help: return argparse's code, so main() always returns
        return int(exc.code or 0) if not isinstance(exc.code, str) else 2
    try:
        return int(args.func(args) or 0)
    except HoiRefineError as exc:
        print(f"hoi-refine: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        if exc.filename is None:  # not about a file the user named (a socket, a pipe): a bug, keep its traceback
            raise
        # A path given on the command line that is missing, a directory or unreadable: say so, not a traceback.
        print(f"hoi-refine: error: {exc.filename}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hoi-refine: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
