"""``comp-daemon trial``: seed 000's experiment end to end through the running daemon.

Brings up the simulated cell and the daemon, runs grating calibration, ISO 9283 with and without
joint feedback, sampling, fits over HTTP and the target points four (to six) ways — the Chebyshev
model with the joint loop both with the daemon's six-axis inverse kinematics and with seed 000's
mapping onto joints 1–3 — and prints Table 2 beside seed 000's figures (:mod:`comp_daemon.trial`).
``--quick`` is the reduced trial of the test suite (about two minutes); the full trial takes about
half an hour. ``--from-json`` renders the report of an earlier run again without running anything.

Exit codes: 0 the trial ran (whatever its numbers); 1 it stopped part way (the partial result is
still written); 2 bad arguments.
"""

from __future__ import annotations

import argparse
import asyncio
import shlex
import sys
import tempfile
import time
from pathlib import Path
from typing import TextIO

from comp_daemon.sim_client import preset_scenarios


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "trial",
        help="run seed 000's experiment on the simulated cell through the daemon and report Table 2",
        description="Seed 000's experiment end to end: the simulated cell and the daemon are brought up, "
        "the gratings calibrated, ISO 9283 run with and without joint feedback, sampling points measured "
        "and models fitted over HTTP, and the target points run uncompensated, with kinematic calibration "
        "and with the Chebyshev model and the joint loop (six-axis inverse kinematics and seed 000's mapping "
        "onto joints 1-3). Prints Table 2 beside seed 000's figures.",
    )
    p.add_argument(
        "--scenario",
        default="kr210-cell",
        help=f"simulated cell: {', '.join(preset_scenarios())} or a scenario TOML (default kr210-cell)",
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the poses and of the cell's noise (default 0)"
    )
    p.add_argument("--payload-kg", type=float, default=0.0, help="payload at the TCP throughout (default 0)")
    p.add_argument(
        "--quick", action="store_true", help="the reduced trial of the test suite (about two minutes)"
    )
    p.add_argument("--order", type=int, default=None, help="Chebyshev order (default 3; 0 with --quick)")
    p.add_argument("--json", metavar="OUT.json", help="write the full result (every measurement) as JSON")
    p.add_argument("--report", metavar="OUT.html", help="write the HTML report")
    p.add_argument(
        "--workdir",
        metavar="DIR",
        help="keep the daemon's data, configuration and log here (default: a temporary directory)",
    )
    p.add_argument("--from-json", metavar="IN.json", help="render the report of an earlier run; runs nothing")
    p.set_defaults(func=_run)


class ProgressPrinter:
    """One line per phase; on a terminal the line updates in place."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.tty = stream.isatty()
        self.t0 = time.monotonic()
        self.last = 0.0
        self.width = 0

    def __call__(self, event: object) -> None:
        from comp_daemon.trial.runner import ProgressEvent

        assert isinstance(event, ProgressEvent)
        elapsed = time.monotonic() - self.t0
        stamp = f"{int(elapsed // 60):>3d}:{int(elapsed % 60):02d}"
        head = f"{stamp} [{event.step:>2}/{event.steps}] {event.phase}"
        if event.finished:
            line = head + (f": {event.note}" if event.note else ": done")
            self._write(line, final=True)
            return
        count = f" {event.done}/{event.total}" if event.total else ""
        line = head + count + (f"  {event.note}" if event.note else "")
        now = time.monotonic()
        if self.tty:
            self._write(line, final=False)
        elif event.done == 0 and event.total == 0 and not event.note:
            self._write(line, final=True)
        elif now - self.last >= 15.0:
            self.last = now
            self._write(line, final=True)

    def _write(self, line: str, *, final: bool) -> None:
        if self.tty:
            pad = max(0, self.width - len(line))
            self.stream.write("\r" + line + " " * pad + ("\n" if final else ""))
            self.width = 0 if final else len(line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


def _write_outputs(result: object, args: argparse.Namespace, command: str) -> None:
    from comp_daemon.trial.report import render_html
    from comp_daemon.trial.result import TrialResult

    assert isinstance(result, TrialResult)
    if args.json:
        Path(args.json).write_text(result.to_json() + "\n", encoding="utf-8")
        print(f"result: {args.json}", file=sys.stderr)
    if args.report:
        Path(args.report).write_text(render_html(result, command=command), encoding="utf-8")
        print(f"report: {args.report}", file=sys.stderr)


def _run(args: argparse.Namespace) -> int:
    from comp_daemon.trial.plan import FULL, QUICK, TrialPlan
    from comp_daemon.trial.report import render_text
    from comp_daemon.trial.result import TrialResult
    from comp_daemon.trial.runner import TrialError, run_trial, with_sizes

    if args.from_json:
        result = TrialResult.load(args.from_json)
        print(render_text(result), end="")
        _write_outputs(result, args, command=str(result.plan.get("command", "")))
        return 0
    sizes = QUICK if args.quick else FULL
    plan = TrialPlan(scenario=args.scenario, seed=args.seed, payload_kg=args.payload_kg, sizes=sizes)
    if args.order is not None:
        plan = with_sizes(plan, chebyshev_order=args.order)
    command = "comp-daemon " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    printer = ProgressPrinter(sys.stderr)
    with tempfile.TemporaryDirectory(prefix="comp-daemon-trial-") as tmp:
        workdir = Path(args.workdir) if args.workdir else Path(tmp)
        print(f"comp-daemon trial: working in {workdir}", file=sys.stderr)
        try:
            result = asyncio.run(run_trial(plan, workdir, progress=printer))
        except TrialError as exc:
            print(f"comp-daemon trial: stopped: {exc}", file=sys.stderr)
            if exc.result is not None:
                exc.result.plan["command"] = command
                _write_outputs(exc.result, args, command)
            return 1
    result.plan["command"] = command
    print(render_text(result), end="")
    _write_outputs(result, args, command)
    return 0
