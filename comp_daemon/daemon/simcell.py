"""The simulated cell beside the daemon (``comp-daemon run --sim``).

The cell runs as a child process (:mod:`comp_daemon.sim.cell`, started by module name through
:mod:`comp_daemon.sim_client`, which the trial uses too); the daemon talks to it over UDP,
pseudo-terminals and TCP exactly as to the line, and imports nothing of the simulator. Its
controller re-arms RSI ``rearm_after_s`` after a stop, as an operator restarting the program does.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from comp_daemon.daemon.gratings import GratingGeometry
from comp_daemon.daemon.motion import LineMotionPort
from comp_daemon.daemon.ports import CellPorts
from comp_daemon.service.config import Settings
from comp_daemon.sim_client import SimCellProcess

__all__ = ["SimOptions", "start_simulated_cell"]


@dataclass(frozen=True, slots=True)
class SimOptions:
    """The simulated cell brought up beside the daemon (``run --sim``)."""

    scenario: str = "kr210-cell"
    seed: int = 0
    servo_lag_cycles: int = 1
    rearm_after_s: float | None = 5.0  # the controller restarts RSI this long after a stop (None: never)


async def start_simulated_cell(
    settings: Settings, options: SimOptions, rsi_port: int
) -> tuple[SimCellProcess, CellPorts]:
    """Start the cell's child against the daemon's RSI port; its process and its ports once it is up."""
    rsi = settings.rsi
    sim = SimCellProcess(
        rsi_port=rsi_port,
        link_dir=Path(settings.store.data_dir) / "sim",
        scenario=options.scenario,
        seed=options.seed,
        cycle_ms=rsi.cycle_ms,
        servo_lag_cycles=options.servo_lag_cycles,
        timeout_count=rsi.timeout_count,
        sen_type=rsi.sen_type,
        rearm_after_s=options.rearm_after_s,
    )
    info = await sim.start()
    ports = CellPorts(
        gratings={j: (path, info.bits) for j, path in info.gratings.items()},
        geometry={j: GratingGeometry(info.radius_mm, info.resolution_nm) for j in info.gratings},
        motion=LineMotionPort(
            info.motion_host, info.motion_port, timeout_s=settings.controller.move_timeout_s
        ),
        home_deg=info.home_deg,
    )
    return sim, ports
