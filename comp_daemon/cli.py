"""The ``comp-daemon`` command line: a dispatcher over the subcommand modules in ``comp_daemon.commands``.

Each module in :data:`COMMAND_MODULES` has ``register(subparsers)``, which adds its subcommand(s) and
sets ``func`` (taking the parsed arguments, returning an exit code) on each parser it adds.
Errors that a user can fix (a bad file, an unknown robot) print one line to stderr and exit 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from comp_daemon import __version__

COMMAND_MODULES: tuple[str, ...] = ("robot", "data", "sim", "run", "diagnose", "fit", "trial")


class UserError(Exception):
    """An error in what the user asked for; printed without a traceback."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="comp-daemon",
        description="Accuracy compensation for a robotic drilling cell: error models, "
        "closed-loop joint feedback over KUKA RSI, sim-to-real gap diagnosis.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        module = importlib.import_module(f"comp_daemon.commands.{name}")
        module.register(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    try:
        return int(func(args) or 0)
    except (UserError, ValueError, OSError) as exc:
        print(f"comp-daemon {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
