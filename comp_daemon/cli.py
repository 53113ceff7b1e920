"""The ``comp-daemon`` command line: a dispatcher over the subcommand modules.

Each module in :data:`COMMAND_MODULES` (``comp_daemon.commands.*``, and the simulator's own
``comp_daemon.sim.cli``) has ``register(subparsers)``, which adds its subcommand(s) and sets ``func``
(taking the parsed arguments, returning an exit code) on each parser it adds. A command in
:data:`ON_DEMAND` is imported only when it is the one that runs (the listing shows its help line),
so ``comp-daemon run`` never loads the simulator. Errors that a user can fix (a bad file, an
unknown robot) print one line to stderr and exit 2.

``--threads N`` (before the command; default 1, or ``COMP_DAEMON_THREADS``) is how many threads
the numeric libraries use in this process and the processes it starts
(:mod:`comp_daemon.common.threads`); it is set before NumPy loads.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from comp_daemon import __version__
from comp_daemon.commands.errors import UserError
from comp_daemon.common.threads import (
    DEFAULT_THREADS,
    THREADS_ENV,
    parse_threads,
    set_numeric_threads,
    threads_from_argv,
)

COMMAND_MODULES: dict[str, str] = {
    "robot": "comp_daemon.commands.robot",
    "data": "comp_daemon.commands.data",
    "sim": "comp_daemon.sim.cli",
    "run": "comp_daemon.commands.run",
    "diagnose": "comp_daemon.commands.diagnose",
    "fit": "comp_daemon.commands.fit",
    "compensate": "comp_daemon.commands.compensate",
    "plan": "comp_daemon.commands.plan",
    "trial": "comp_daemon.commands.trial",
    "export": "comp_daemon.commands.export",
    "store": "comp_daemon.commands.store",
}
#: commands whose module is imported only to run them, with the help line of the command listing
ON_DEMAND: dict[str, str] = {"sim": "the simulated drilling cell: measurement campaigns, figures"}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command; of those in :data:`ON_DEMAND` only ``command`` is complete."""
    parser = argparse.ArgumentParser(
        prog="comp-daemon",
        description="Accuracy compensation for a robotic drilling cell: error models, "
        "closed-loop joint feedback over KUKA RSI, sim-to-real gap diagnosis.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument(
        "--threads",
        type=_threads_arg,
        default=None,
        metavar="N",
        help=f"threads of the numeric libraries (BLAS, OpenMP) per process (default {DEFAULT_THREADS}, "
        f"or {THREADS_ENV}); parallel work runs in processes instead (evaluate --jobs)",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name in COMMAND_MODULES.items():
        if name in ON_DEMAND and name != command:
            subparsers.add_parser(name, help=ON_DEMAND[name])
            continue
        importlib.import_module(module_name).register(subparsers)
    return parser


def _threads_arg(text: str) -> int:
    try:
        return parse_threads(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def main(argv: Sequence[str] | None = None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    try:  # before the command modules load NumPy
        set_numeric_threads(threads_from_argv(words))
    except ValueError as exc:
        print(f"comp-daemon: error: {exc}", file=sys.stderr)
        return 2
    parser = build_parser(next((w for w in words if not w.startswith("-")), None))
    args = parser.parse_args(words)
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
