"""The simulated cell, a process of its own (``python -m comp_daemon.sim.cell …``).

It runs its own event loop with the scenario's hidden robot (:class:`comp_daemon.sim.plant.RobotPlant`),
the simulated KR C4 sending RSI telegrams to the daemon's UDP port, one grating converter per grating
joint on a pseudo-terminal (reachable through a stable symlink, as ``/dev/serial/by-id/…`` on the
line) and the laser tracker. Being a separate process it has its own interpreter and scheduler, as
the robot controller has on the line: the plant's physics never runs inside the daemon's RSI path,
and a busy daemon makes the controller count late replies exactly as a real one would. The daemon
(``comp-daemon run --sim``) and the trial start it through :class:`comp_daemon.sim_client.SimCellProcess`.

Interfaces (all on 127.0.0.1):

- RSI: UDP client to ``--rsi-host``/``--rsi-port``.
- Motion (the controller's command port): ``move A1 … A6`` → ``OK arrived`` | ``ERR <why>``,
  ``rsi_on``, ``rsi_off``, ``status``.
- Cell port: ``measure`` → ``OK x y z`` (tracker frame, with noise); ``tcp`` → ``OK x y z`` (true TCP,
  robot base frame); ``joints`` → ``OK a1 … a6`` (true output angles, deg); ``fault J KIND`` /
  ``clear J`` (converter fault injection: bad_crc, error_bit, warning_bit, silent, garble);
  ``unplug J`` / ``replug J``; ``payload KG``; ``status`` → ``OK <json>``.

RSI starts when a client sends ``rsi_on`` on the motion port (as the robot program's ``RSI_ON`` once
the operator starts it), or at once with ``--rsi-on``. With ``--rearm-after-s S`` the controller
restarts RSI S seconds after each stop (late replies, Stop=1, AXISCORRMON), as the operator does on
the line; the motion port's ``status`` lists the stops with their causes. On start the cell prints
one JSON line on stdout (ports, grating symlinks, converter geometry:
:class:`comp_daemon.sim_client.SimCellInfo`) and then serves until SIGTERM/SIGINT, when it stops
RSI, unplugs the converters and exits 0. With ``--exit-with-parent`` (how the daemon starts it) it
does the same when its stdin reaches end of file: the parent holds the pipe's other end, so a daemon
killed with SIGKILL leaves no simulated cell behind sending telegrams. Logs go to stderr. A scenario
that cannot be loaded exits 2 with the reason on stderr, before the ready line.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path

from comp_daemon.common.logs import configure_logging, get_logger
from comp_daemon.sim.converter import ConverterConfig, ConverterFault, SimulatedConverter
from comp_daemon.sim.plant import RobotPlant
from comp_daemon.sim.rsi_controller import RsiControllerConfig, SimulatedRsiController, serve_lines
from comp_daemon.sim.scenario import PRESET_SCENARIOS, Scenario, ScenarioError, load_scenario
from comp_daemon.sim.tracker import LaserTracker
from comp_daemon.sim_client import SimCellInfo

__all__ = ["main"]

log = get_logger(__name__)

CONVERTER_ZERO_DEG = -200.0
CONVERTER_BITS = 26


#: The converter commands of the cell port and how many words follow each (the joint first).
_CONVERTER_ARITY = {"fault": 2, "clear": 1, "unplug": 1, "replug": 1}


class CellCommands:
    """The cell port's line commands (module docstring) on the plant, the tracker, the RSI
    controller and the converters: one line in, one ``OK …`` or ``ERR <why>`` out."""

    def __init__(
        self,
        plant: RobotPlant,
        tracker: LaserTracker,
        controller: SimulatedRsiController,
        converters: Mapping[int, SimulatedConverter],
    ) -> None:
        self.plant = plant
        self.tracker = tracker
        self.controller = controller
        self.converters = converters
        self._queries: dict[str, Callable[[], str]] = {
            "measure": lambda: _numbers(tracker.measure(plant.tcp_true_mm()), 6),
            "tcp": lambda: _numbers(plant.tcp_true_mm(), 6),
            "joints": lambda: _numbers(plant.output_angles_deg(), 8),
            "status": self._status,
        }

    async def __call__(self, line: str) -> str:
        words = line.split()
        if not words:
            return "ERR empty command"
        name, rest = words[0].lower(), words[1:]
        try:
            answer = self._answer(name, rest)
        except (ValueError, RuntimeError) as exc:
            return f"ERR {exc}"
        return f"ERR unknown command {line[:40]!r}" if answer is None else answer

    def _answer(self, name: str, rest: list[str]) -> str | None:
        """The answer to command ``name`` with its words ``rest``; None for a command not known."""
        if name in self._queries and not rest:
            return "OK " + self._queries[name]()
        if name in _CONVERTER_ARITY and rest:
            return self._converter(name, rest)
        if name == "payload" and len(rest) == 1:
            self.plant.set_payload(float(rest[0]))
            return "OK"
        return None

    def _converter(self, name: str, rest: list[str]) -> str:
        conv = self.converters.get(int(rest[0]))
        if conv is None:
            return f"ERR no grating on joint {rest[0]}"
        if len(rest) != _CONVERTER_ARITY[name]:
            return f"ERR bad arguments to {name}"
        if name == "fault":
            conv.inject(ConverterFault(rest[1]))
        elif name == "clear":
            conv.clear()
        elif name == "unplug":
            conv.unplug()
        else:
            conv.replug()
        return "OK"

    def _status(self) -> str:
        doc = {
            "controller": self.controller.status(),
            "correction_deg": self.plant.correction_deg().tolist(),
            "output_deg": self.plant.output_angles_deg().tolist(),
            "converters": {str(j): sorted(map(str, c.faults)) for j, c in self.converters.items()},
        }
        return json.dumps(doc)


def _numbers(values: Iterable[float], decimals: int) -> str:
    return " ".join(f"{v:.{decimals}f}" for v in values)


def _stop_when_parent_goes(loop: asyncio.AbstractEventLoop, stop: asyncio.Event) -> None:
    """Set ``stop`` when stdin reaches end of file: the parent, which holds the pipe's other end, is gone."""
    stdin_fd = sys.stdin.fileno()

    def parent_gone() -> None:
        try:
            data = os.read(stdin_fd, 4096)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            loop.remove_reader(stdin_fd)
            log.warning("the parent process closed the pipe; stopping")
            stop.set()

    loop.add_reader(stdin_fd, parent_gone)


async def _run_cell(args: argparse.Namespace, scenario: Scenario) -> int:
    plant = RobotPlant.from_scenario(scenario, seed=args.seed, payload_kg=args.payload_kg)
    controller = SimulatedRsiController(
        RsiControllerConfig(
            server_host=args.rsi_host,
            server_port=args.rsi_port,
            cycle_ms=args.cycle_ms,
            servo_lag_cycles=args.servo_lag_cycles,
            timeout_count=args.timeout_count,
            sen_type=args.sen_type,
            rearm_after_s=args.rearm_after_s,
        ),
        plant,
    )
    tracker = LaserTracker(scenario.noise.tracker_sigma_mm, scenario.tracker_T_base(), seed=args.seed + 1)
    link_dir = Path(args.link_dir)
    link_dir.mkdir(parents=True, exist_ok=True)
    joints = scenario.cell.grating_joints
    radius = scenario.cell.grating_radius_mm
    converters: dict[int, SimulatedConverter] = {}
    for j in joints:
        cfg = ConverterConfig(
            joint=j,
            radius_mm=radius,
            zero_deg=CONVERTER_ZERO_DEG,
            bits=CONVERTER_BITS,
            link_path=str(link_dir / f"grating-a{j}"),
        )
        converters[j] = SimulatedConverter(cfg, plant)
        converters[j].start()

    cell_command = CellCommands(plant, tracker, controller, converters)

    await controller.start(rsi_on=args.rsi_on)
    motion_host, motion_port = await controller.serve_commands("127.0.0.1", 0)
    cell_server = await asyncio.start_server(
        lambda r, w: serve_lines(r, w, cell_command), "127.0.0.1", args.cell_port
    )
    cell_host, cell_port = cell_server.sockets[0].getsockname()[:2]

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    if args.exit_with_parent:
        _stop_when_parent_goes(loop, stop)
    info = SimCellInfo(
        pid=os.getpid(),
        motion_host=motion_host,
        motion_port=motion_port,
        cell_host=str(cell_host),
        cell_port=int(cell_port),
        rsi_local_port=controller.local_address[1],
        gratings={j: c.port for j, c in converters.items()},
        radius_mm=radius,
        zero_deg=CONVERTER_ZERO_DEG,
        resolution_nm=converters[joints[0]].config.resolution_nm if joints else 50.0,
        bits=CONVERTER_BITS,
        home_deg=tuple(float(v) for v in scenario.campaign.home_deg),
        cycle_ms=args.cycle_ms,
    )
    sys.stdout.write(info.to_json() + "\n")
    sys.stdout.flush()
    await stop.wait()
    cell_server.close()
    await controller.close()
    for conv in converters.values():
        conv.close()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m comp_daemon.sim.cell", description=__doc__)
    parser.add_argument(
        "--scenario", default="kr210-cell", help=f"preset ({', '.join(PRESET_SCENARIOS)}) or a scenario TOML"
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--payload-kg", type=float, default=0.0)
    parser.add_argument("--rsi-host", default="127.0.0.1")
    parser.add_argument("--rsi-port", type=int, required=True)
    parser.add_argument("--cycle-ms", type=int, default=12, choices=(4, 12))
    parser.add_argument("--servo-lag-cycles", type=int, default=1)
    parser.add_argument("--timeout-count", type=int, default=10)
    parser.add_argument("--sen-type", default="ImFree")
    parser.add_argument(
        "--rearm-after-s",
        type=float,
        default=None,
        help="restart RSI this many seconds after a stop, as an operator re-selecting the program "
        "(not after RSI_OFF; default: RSI stays stopped)",
    )
    parser.add_argument("--cell-port", type=int, default=0)
    parser.add_argument("--link-dir", required=True)
    parser.add_argument(
        "--rsi-on", action="store_true", help="start RSI at once (default: wait for the rsi_on command)"
    )
    parser.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="stop as on SIGTERM when stdin reaches end of file (the parent holds the pipe's other end)",
    )
    args = parser.parse_args(argv)
    configure_logging("WARNING", "console")
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as exc:
        print(f"simulated cell: {exc}", file=sys.stderr)
        return 2
    return asyncio.run(_run_cell(args, scenario))


if __name__ == "__main__":
    raise SystemExit(main())
