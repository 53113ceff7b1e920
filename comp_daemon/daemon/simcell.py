"""The daemon's handle on the simulated cell (``comp-daemon run --sim``).

The cell runs as a child process (:mod:`comp_daemon.sim.cell`, started by module name); the handle
is :mod:`comp_daemon.rt.simcell`, shared with the trial. The daemon imports nothing of the simulator.
"""

from __future__ import annotations

from comp_daemon.rt.simcell import SimCellInfo, SimCellProcess, floats, line_command

__all__ = ["SimCellInfo", "SimCellProcess", "floats", "line_command"]
